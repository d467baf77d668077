"""Ray-traced scenes: geometry from configs, Sionna RT tracing, Bartlett spectra, resumable datasets."""

from graf.sim.backend import configure_llvm

configure_llvm()  # before anything imports drjit (Sionna RT's CPU backend needs LLVM >= 15)
