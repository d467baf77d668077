"""Analyses of the data rather than methods: they may look at the truth (see :mod:`.oracle`)."""
