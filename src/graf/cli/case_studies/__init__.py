"""Commands of the case studies: graf-aoa, graf-interp, graf-localize, graf-oracle."""
