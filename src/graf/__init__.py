"""GRaF: an experiment platform for RF spatial-spectrum synthesis."""

__version__ = "0.1.0"

from graf.plugins import load_plugins  # noqa: E402

load_plugins()  # GRAF_PLUGINS: metrics, study axes and methods of the user's own (graf.plugins)
