"""GRaF: an experiment platform for RF spatial-spectrum synthesis."""

__version__ = "0.1.0"
