"""The case studies: what synthesized spectra are good for and why the method works: angle of arrival
(graf-aoa), localization (graf-localize), the interpolation theorem (graf-interp), the oracle (graf-oracle) and
synthesis at new positions (graf-synthesize)."""
