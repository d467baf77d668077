"""The Hydra configs of every graf command (``pkg://graf.conf``), shipped in the wheel.

This file only makes the folder an importable package, which Hydra's ``pkg://`` config source needs;
the YAML groups below it are package data, not Python packages.  ``conf/`` at the top of the checkout
is a symlink to this folder.
"""
