"""Ray-traced scenes: geometry from configs, Sionna RT tracing, Bartlett spectra, resumable datasets, and the
simulator's tasks (graf-simulate: :mod:`.simulate`, graf-bench-sim: :mod:`.benchmark`, graf-show-scenes:
:mod:`.show`)."""

from graf.sim.backend import configure_llvm

configure_llvm()  # before anything imports drjit (Sionna RT's CPU backend needs LLVM >= 15)
