"""What a claim reads of its record: a figure at a dotted key, why the record is below the paper's density, and
the bench timings it reads that its record marks as disturbed (not trusted)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from graf.errors import ConfigError


def lookup(record: dict, key: str):
    """``record`` at the dotted ``key`` (a part may hold ``/``: ``metrics.test/psnr``); KeyError naming the part."""
    node = record
    for part in key.split("."):
        if isinstance(node, list):
            node = node[int(part)]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            raise KeyError(part)
    return node


def density_reason(record: dict) -> str | None:
    """Why a record is not at the paper's density (its scenes cut to ``sim_num_tx`` positions, or the embedded
    slice of a real scene), or None."""
    scenes = ((record.get("config") or {}).get("scene") or {}).values()
    slices = sorted({str(s.get("name")) for s in scenes if str(s.get("path", "")).startswith("embedded:")})
    if slices:
        n = record.get("n_train", 0) + record.get("n_test", 0)
        return f"made on the embedded {n}-position slice of {', '.join(slices)} (the paper: the whole scene)"
    n = record["sim_num_tx"] if "sim_num_tx" in record else (record.get("config") or {}).get("sim_num_tx")
    counts = [c for c in (n if isinstance(n, list) else [n]) if c is not None]
    if not counts:
        return None
    return f"made on {', '.join(map(str, counts))} positions per simulated layout (the paper: about 5,400)"


TIMING_KEY = re.compile(r"^rows\.(\d+)\.((infer|train)_\w+)$")  # a bench row's timing: its phase's disturbances


def untrusted_timings(claim: dict, record: dict) -> list[str]:
    """The disturbances its record marks on the bench timings a claim reads (``key``, ``over``, ``minus`` of the
    form ``rows.N.infer_...`` or ``rows.N.train_...``): the phase's entries of the row's ``disturbances`` (load or a
    spread of repeated timings beyond graf-bench's limits), each naming its row."""
    out = []
    for field in ("key", "over", "minus"):
        m = TIMING_KEY.match(str(claim.get(field) or ""))
        rows = record.get("rows") if m else None
        if not m or not isinstance(rows, list) or int(m.group(1)) >= len(rows):
            continue
        row = rows[int(m.group(1))]
        phase = m.group(3)
        found = [d for d in row.get("disturbances") or [] if str(d).startswith(f"{phase}:")]
        out += [f"{row.get('preset') or row.get('method')} on {row.get('scene')}: {d}" for d in found]
    return out


def load_record(root: Path, rel: str) -> dict | None:
    path = root / rel
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not readable JSON ({exc})") from None
