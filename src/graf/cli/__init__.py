"""The commands: thin Hydra entry points, one file per console script (config in, one call, exit code out), and
what they share (:mod:`.entry`: where the configs are, how a command ends on an error).  Importing it
makes a Ctrl+C during the imports that follow one line and exit code 130 (:func:`graf.interrupts.install`)."""

from graf.interrupts import install

install()
