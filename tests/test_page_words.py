"""The site's build checks on what a page says (docs_hooks/page_words.py): no development-log words on a user page,
and every shell block valid bash, so that a command copied from the site runs when pasted."""

from __future__ import annotations

import shutil

import pytest
from docs_hooks import page_words


def test_development_log_words_are_found_on_user_pages_only():
    page = "\n".join(
        [
            "The choice of issue 53 ran on a lent GPU.",  # 2 words
            "Finished at home, in a later session.",  # 2 words
            "Measured on the 2-core Intel Xeon.",  # a machine in prose
            "| rfid_sparse | nerf2 | 22.31 | NVIDIA H200 |",  # a record's device column: its provenance
            "graf-bench on Intel(R) Xeon(R) Processor (cpu, 1 threads)",  # graf-bench's header: its provenance
            "A lentil is not a lent machine.",  # a word that contains one is not it; "lent" alone is
        ]
    )
    found = page_words.development_words(page, "studies.md")
    assert [f.split(": ", 1)[1].split(" (")[0] for f in found] == [
        "'issue 53'", "'lent'", "'at home'", "'session'", "'Xeon'", "'lent'",
    ]  # fmt: skip
    assert [f.split(":")[1] for f in found] == ["1", "1", "2", "2", "3", "6"]
    assert page_words.development_words(page, "reproducibility.md") == []  # the log's subject


@pytest.mark.skipif(shutil.which("bash") is None, reason="no bash")
def test_a_shell_block_that_bash_cannot_parse_is_named():
    page = "\n".join(
        [
            "```bash",
            "bash scripts/paper_studies_gpu.sh OUT .paper_gpu --deadline <seconds>",
            "```",
            "",
            "    ```bash",
            "    graf-train experiment=graf_rfid_s23 \\",
            "        trainer.max_steps=100",
            "    ```",
            "",
            "```yaml",
            "a: <b>",
            "```",
        ]
    )
    assert len(page_words.shell_blocks(page)) == 2  # the yaml block is not shell
    problems = page_words.shell_problems(page, "scaling-out.md")
    assert len(problems) == 1 and problems[0].startswith("scaling-out.md: ") and "deadline <seconds>" in problems[0]


def site_commands() -> list[tuple[str, str, list[str]]]:
    """``(page, command, arguments)`` of every graf command in a shell block of the site's pages (continued lines
    joined; a leading ``VAR=value`` and ``.venv/bin/`` dropped; a trailing comment left out)."""
    import re
    import shlex
    from pathlib import Path

    out = []
    for page in sorted((Path(__file__).resolve().parents[1] / "docs").rglob("*.md")):
        for body in page_words.shell_blocks(page.read_text()):
            for line in re.sub(r"\\\n\s*", " ", body).split("\n"):
                m = re.match(r"^\s*(?:\w+=\S+\s+)*(?:\.venv/bin/)?(graf-[\w-]+)(?=\s|$)(.*)$", line)
                if m:
                    out.append((page.name, m.group(1), shlex.split(m.group(2), comments=True)))
    return out


CHECK = """
import json, sys
from graf.app.overrides import check_overrides
from graf.errors import UserError
problems = []
for page, config, args in json.loads(sys.stdin.read()):
    try:
        check_overrides(config, args)
    except UserError as exc:
        problems.append(f"{page}: {config} {' '.join(args)}: {exc}")
print(json.dumps(problems))
"""


@pytest.mark.slow  # about half a minute: every graf command of the site composed
def test_every_graf_command_on_the_site_composes():
    """Every graf command in a shell block of the site composes its config as pasted (graf's own check of a command
    line, as the command runs it: an unknown option, a key that does not exist, a syntax error), with no placeholder
    left; Hydra's own flags (``--cfg job``) are Hydra's.  The extension page's commands run with its plugin loaded
    (``GRAF_PLUGINS=toy_plugin``, as the page exports); a command reading a config folder the reader makes on that
    page (``hydra.searchpath=[file://$PWD/my_conf]``) is left out: its files are the reader's."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "docs_hooks"))  # as MkDocs loads the hooks
    import reference

    configs = reference.commands()
    commands = site_commands()
    assert len(commands) > 80
    problems, jobs = [], {"": [], "toy_plugin": []}
    for page, command, args in commands:
        args = [a for a in args if a not in ("-m", "--multirun")]
        if "--cfg" in args:
            del args[args.index("--cfg") : args.index("--cfg") + 2]
        if any("$PWD/my_conf" in a for a in args):
            continue
        if any(a in ("...", "…") or "<" in a for a in args):
            problems.append(f"{page}: {command} {' '.join(args)}: a placeholder, not a command")
            continue
        jobs["toy_plugin" if page == "extending.md" else ""].append((page, configs[command], args))
    for plugins, batch in jobs.items():
        env = {**os.environ, "GRAF_PLUGINS": plugins}
        env["PYTHONPATH"] = os.pathsep.join([str(root / "tests" / "plugins"), env.get("PYTHONPATH", "")])
        p = subprocess.run([sys.executable, "-c", CHECK], input=json.dumps(batch), env=env, capture_output=True,
                           text=True, timeout=600, cwd=root)  # fmt: skip
        assert p.returncode == 0, p.stderr[-3000:]
        problems += json.loads(p.stdout.strip().splitlines()[-1])
    assert problems == [], "\n".join(problems)
