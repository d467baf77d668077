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
