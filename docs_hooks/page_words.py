"""Build checks on what a page says, after its generated blocks are expanded (``hooks.on_page_markdown``):

- :func:`development_words`: no development-log words on a user page ("issue N", "lent", "session", "at home",
  and the machines' names but where they are a measurement's provenance: a table's row, graf-bench's header);
  the reproducibility log (:data:`LOG_PAGES`), whose subject they are, is exempt;
- :func:`shell_problems`: every shell block of a page is valid bash (``bash -n``), so that a command copied from the
  site runs when pasted.
"""

from __future__ import annotations

import re
import shutil
import subprocess

LOG_PAGES = ("reproducibility.md",)  # the log of what ran where: its subject is the development itself
DEV_WORDS = re.compile(r"\bissues? \d+|\blent\b|\bsessions?\b|\bat home\b", re.IGNORECASE)
MACHINES = re.compile(r"\b(?:H200|H100|A100|EPYC|Xeon|Ryzen)\b", re.IGNORECASE)
# where a machine's name is the measurement's own provenance (the house rule: say which machine a figure came
# from): a table's row (a record's device column) and graf-bench's header line naming the device it ran on
PROVENANCE = re.compile(r"^\s*(?:\||graf-bench on )")
FENCE = re.compile(r"^(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.M | re.S)
SHELL = ("bash", "sh", "shell", "console")


def development_words(markdown: str, src_uri: str) -> list[str]:
    """``page:line: word (the line)`` for every development-log word on the page (none on a log page)."""
    if src_uri.rsplit("/", 1)[-1] in LOG_PAGES:
        return []
    out = []
    for n, line in enumerate(markdown.split("\n"), 1):
        found = list(DEV_WORDS.finditer(line))
        if not PROVENANCE.match(line):
            found += list(MACHINES.finditer(line))
        out += [f"{src_uri}:{n}: {m.group(0)!r} ({line.strip()[:120]})" for m in found]
    return out


def shell_blocks(markdown: str) -> list[str]:
    """The bodies of the page's fenced shell blocks (```bash, sh, shell, console)."""
    return [m["body"] for m in FENCE.finditer(markdown) if m["lang"].lower() in SHELL]


def shell_problems(markdown: str, src_uri: str) -> list[str]:
    """``page: bash -n's complaint (the block's first line)`` for every shell block bash cannot parse."""
    bash = shutil.which("bash")
    if bash is None:
        return []
    out = []
    for body in shell_blocks(markdown):
        text = "\n".join(line.removeprefix("$ ") for line in body.split("\n"))
        p = subprocess.run([bash, "-n"], input=text, capture_output=True, text=True)
        if p.returncode:
            first = next((ln for ln in body.split("\n") if ln.strip()), "")
            out.append(f"{src_uri}: {p.stderr.strip().splitlines()[-1]} (block: {first.strip()[:100]})")
    return out
