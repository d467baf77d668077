"""graf-claims: the ledger of the paper's quantitative claims against the platform's records.

Each claim of ``conf/claims.yaml`` names what the paper's supplement says, the platform record that answers it and
how (``kind``):

- ``paired``: rows of a study's ``intervals.json`` (:mod:`graf.reports.intervals`) selected by their cell
  settings; the paper says ``method`` is ahead of ``reference`` on ``metric``.  Holds when every selected cell's
  interval says ahead, refuted when one says behind, not reproduced when an interval includes 0.  A target's
  ``margin`` (ahead by at least this much in every cell, the interval excluding 0) or ``share`` (better on at least
  this share of each cell's spectra) is judged instead where given: holds when every cell reaches it, else not
  reproduced, with the cell that falls furthest short and by how much.
- ``value``: one figure of a JSON record (``key``: a dotted path, ``/`` kept inside names) against the paper's
  ``paper_value``; holds when it reaches it in the better direction (``higher_is_better``), else not reproduced.
- ``difference``: two figures of a record (``key`` minus ``minus``) against the paper's difference, the same rule.
- ``change``: a change with L of the neighbor-count study (``intervals.json`` ``L_changes``: ``method``,
  ``L_from``, ``L_to``, ``metric``).  With ``tolerance``: holds when the whole interval lies within it (a plateau);
  else holds when the interval excludes 0 on the paper's side (the sign of ``paper_value``), refuted when it
  excludes 0 on the other, not reproduced when it includes 0.
- ``transfer``: the bands study's ``band_transfers`` (a model trained at another band minus the one trained at the
  test band, on the same spectra; ``method``, ``metric``); the paper says the transfer is ``expect`` (``behind``).
  Holds when every pair's interval says so, refuted when one says the other way, not reproduced when one includes 0.
- ``note``: a claim the platform cannot check on its own terms (another GPU, another unit): not comparable, with
  the platform's figure where it has one.
- ``distance``: not a claim of the paper but a finding of the platform's own (:mod:`.findings`): a
  neighbour-distance record's ``method`` minus ``reference`` at every family and distance; its verdict says where
  the method leads, trails or is level, in a part of the page of its own, counted apart from the claims.

Every claim may require the paper's density (``paper_density: true``): a record made on scenes cut below it (its
``sim_num_tx``, or ``config.sim_num_tx``, set; or the embedded slice of a real scene) makes the verdict "not
comparable" with the count, its figure and interval still shown.  A claim whose
record is missing is "not reproduced (no record)".

The claims are ``conf/claims.yaml``'s, or the user's own file: ``claims=<file>``, or a ``claims.yaml`` in a config
folder of the user's (``--config-dir``), which graf's own file of that name would otherwise hide
(:func:`graf.reports.claims.claims_file.read_claims`).  A file that cannot be read, or a claim lacking what its kind
reads, stops the command with one line naming the file and the problem, as does a ``records`` folder that does not
exist.  A claim may be a re-run of an earlier one (``of``: the same claim on another record, at other budgets;
``variant`` names how it differs): a part of that claim's section with its own verdict, not counted again.

The ledger is ``claims.csv`` (the machine form) and ``results.json`` in ``out``, and the page to read, ``claims.md``
(the docs page includes it), with a forest plot ``<id>.png`` per claim with intervals
(:mod:`graf.reports.claims.ledger`; a claim's ``title`` heads its section, and a ``paper_value`` of a paired claim is
drawn on its plot); its inputs are the records alone, so it is rebuilt from them.  The rooms: :mod:`.judge` (the
verdicts and the command), :mod:`.records` (what a claim reads of its record), :mod:`.claims_file` (the claims
themselves), :mod:`.ledger` (the page).
"""

from graf.reports.claims.judge import claim_cells, claims, judge, ledger, write_ledger

__all__ = ["claim_cells", "claims", "judge", "ledger", "write_ledger"]
