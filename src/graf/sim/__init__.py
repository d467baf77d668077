"""Ray-traced scenes: geometry from configs, Sionna RT tracing, Bartlett spectra, resumable datasets."""
