"""A Ctrl+C at any stage of a command ends it on one line with exit code 130: the stage it came in, what was kept
and how to go on, never a traceback.

The stage is ``start-up`` (the imports, the config) until a command marks another (:func:`stage`: graf-train's and
graf-eval's ``set-up`` and ``testing``, a command's own name otherwise), which gives the KeyboardInterrupt its
line; the commands' decorator (:func:`graf.cli.entry.graf_command`) prints it and exits with code 130.
Training has its own (``graf.run.resume.interrupted``: the step it stopped at and the command that resumes it).
A SIGTERM stops a command the same way in every stage (:func:`install_sigterm`): exit code 143, the stage and what
was kept; in training after the step in progress, saved (``graf.run.resume.preempted``).
:func:`install`, run when :mod:`graf.cli` is imported (before torch is), does the same for a Ctrl+C during the
imports.  Once a command is ending on an interrupt a second Ctrl+C is ignored (:func:`ignore_further`).
Standard library only: it costs nothing at start-up.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

__all__ = [
    "INTERRUPTED_EXIT_CODE",
    "TERMINATED_EXIT_CODE",
    "Terminated",
    "current_stage",
    "ignore_further",
    "install",
    "install_sigterm",
    "interrupted_line",
    "stage",
]

INTERRUPTED_EXIT_CODE = 130  # 128 + SIGINT: what a shell reports for a command stopped by Ctrl+C
TERMINATED_EXIT_CODE = 143  # 128 + SIGTERM (graf.errors.PREEMPTED_EXIT_CODE)
_STAGE = ["start-up"]
_KEPT: list = [None]  # each stage's "what was kept" (a callable or None), beside _STAGE


class Terminated(Exception):
    """A SIGTERM outside training (set-up, validation, testing, writing): the command stops with the stage it came
    in and what was kept, exit code 143, like a pre-empted training (which saves its step first)."""

    exit_code = TERMINATED_EXIT_CODE

    def __init__(self, line: str, said_kept: bool):
        super().__init__(line)
        self.said_kept = said_kept


_PREVIOUS_HOOK = [sys.__excepthook__]


def current_stage() -> str:
    return _STAGE[-1]


@contextlib.contextmanager
def stage(name: str, kept=None):
    """The command is in stage ``name`` within this block.  A KeyboardInterrupt leaving it carries its line
    (``said``: :func:`interrupted_line` with ``kept()``, what was kept and how to go on) for the command to print;
    it is raised on as it is, so a caller in Python sees the KeyboardInterrupt."""
    _STAGE.append(name)
    _KEPT.append(kept)
    try:
        yield
    except KeyboardInterrupt as exc:
        if not getattr(exc, "said", None):  # the innermost stage says it
            exc.said = interrupted_line(kept() if kept else "")
        raise
    finally:
        _STAGE.pop()
        _KEPT.pop()


def interrupted_line(detail: str = "") -> str:
    """``interrupted (Ctrl+C) during <stage>; <detail>``."""
    return f"interrupted (Ctrl+C) during {current_stage()}" + (f"; {detail}" if detail else "")


def ignore_further() -> None:
    """A second Ctrl+C while the command ends on the first is ignored (it printed a second traceback)."""
    with contextlib.suppress(ValueError):  # not the main thread: no signal handlers there
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _on_uncaught(kind, value, tb) -> None:
    if not issubclass(kind, KeyboardInterrupt):
        _PREVIOUS_HOOK[0](kind, value, tb)
        return
    ignore_further()
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    print(interrupted_line("nothing was run: run the command again"), file=sys.stderr, flush=True)
    os._exit(INTERRUPTED_EXIT_CODE)  # the interpreter would end by SIGINT itself (-2), after its own traceback


def _on_sigterm(signum, frame) -> None:
    """SIGTERM: in training, nothing here (Lightning's signal connector, which calls this handler too, stops the fit
    after the step in progress and graf-train saves it: :class:`graf.callbacks.Preemption`); in any other stage the
    command stops now with :class:`Terminated` (the stage, what was kept)."""
    if current_stage() == "training":
        return
    kept = next((k for k in reversed(_KEPT) if k is not None), None)
    detail = kept() if kept else ""
    raise Terminated(f"stopped by SIGTERM during {current_stage()}" + (f"; {detail}" if detail else ""), bool(detail))


def install_sigterm() -> None:
    """Make a SIGTERM stop the command the same way in every stage (:func:`_on_sigterm`); the main thread only."""
    with contextlib.suppress(ValueError):  # not the main thread: no signal handlers there
        signal.signal(signal.SIGTERM, _on_sigterm)


def install() -> None:
    """A KeyboardInterrupt that nothing caught (a Ctrl+C while the command imports) ends the process with
    :func:`interrupted_line` and exit code 130; any other uncaught exception is reported as before."""
    if sys.excepthook is not _on_uncaught:
        _PREVIOUS_HOOK[0] = sys.excepthook
        sys.excepthook = _on_uncaught
