"""graf plugins' own conf folders on Hydra's search path, discovered through the ``hydra_plugins`` namespace: a
plugin registers its folder once (:func:`graf.plugins.add_conf`) and every graf command finds its configs."""
