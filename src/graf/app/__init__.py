"""The command framework every command uses: where the configs are and what a config selects (scenes, bands,
held-out layouts), the task wrapper, the command line checked and brought up to date before Hydra composes,
the output folder checked, and how a command ends."""
