"""The commands: thin Hydra entry points, one file per console script (config in, one call, exit code out), and
what they share (:mod:`.entry`: where the configs are, how a command ends on an error)."""
