"""Reports over the records of many runs: graf-report (a study folder's tables, paired intervals and figures),
graf-table, graf-claims (the claims ledger), the study axes, and the tables the site shows (``published``)."""
