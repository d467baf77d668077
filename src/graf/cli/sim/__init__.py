"""Commands of the simulator: graf-simulate, graf-bench-sim, graf-show-scenes."""
