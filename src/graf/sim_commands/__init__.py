"""The simulator's commands over :mod:`graf.sim`: simulate a scene (graf-simulate), benchmark the tracer
(graf-bench-sim), show the scenes (graf-show-scenes)."""
