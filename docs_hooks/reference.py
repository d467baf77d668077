"""The reference pages' generated blocks: every command's options and every config group's options, read from the
configs in ``src/graf/conf`` when the site is built, so that a key, its default and its comment are never copied by
hand.

Two directives, each on a line of its own (:func:`expand` replaces them):

- ``<!-- gen: config NAME -->``: the settings of a config file as a table (key, default, the file's comment on it).
  ``NAME`` is a console script (``graf-train``: the root config its command composes, found from ``pyproject.toml``
  and the ``@graf_command("...")`` decorator of its module) or a file under ``src/graf/conf`` (``data/default.yaml``).
  A command's table is preceded by the config groups it composes, with their default options.
- ``<!-- gen: group NAME -->``: the options of config group ``NAME`` (its ``*.yaml`` files, the shared ``base/``
  files left out), each with the first sentence of its file's comment.
- ``<!-- gen: interp PATH[,PATH...] -->``: the interpolation case study's figures, one row per scene of each
  graf-interp record (``sweeps/interpolation/<run>``; its ``results.json``), as the Case studies page shows them.

Comments are read from the YAML's lines: the comment on a key's line (and the comment lines aligned under it), or
else the comment lines just above the key.  A nested block of settings (``bench:``) is listed key by key; a block of
named entries (``regimes:``, ``points:``) is one row naming them.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import tree_pages
import yaml
from mkdocs.exceptions import PluginError

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "src" / "graf" / "conf"
DIRECTIVE = re.compile(r"^<!-- gen: (config|group|interp|settings) (\S+) -->$", re.M)
# what the keys every command shares set, where a config file leaves them without a comment
BUILT_IN = {
    "task_name": "names the output folder (`outputs/<task_name>/<time>/`) and its log file",
    "seed": "the run's seed: initial weights, the training stream, every seeded draw",
    "data_root": "where datasets are read from and written to",
    "_target_": "the class these settings construct",
    "reliance_seed": "the seed of the neighbor swap (a derangement) of `reliance`",
}


def expand(markdown: str, src_uri: str = "", fit=None) -> str:
    """``markdown`` with every ``config`` and ``group`` directive replaced by its table; ``src_uri`` (the page's
    path under ``docs/``) makes the links to the config groups' sections relative to the page; ``fit`` (text ->
    text), when given, shapes each generated block (the hooks split a table too wide for its page)."""
    depth = src_uri.count("/")

    def one(m: re.Match) -> str:
        kind, name = m.group(1), m.group(2)
        try:
            makers = {"config": lambda: config_block(name, depth), "group": lambda: group_block(name),
                      "interp": lambda: interp_table(name), "settings": lambda: settings_table(name)}  # fmt: skip
            text = makers[kind]()
            return fit(text) if fit else text
        except (OSError, ValueError, KeyError, yaml.YAMLError, tree_pages.TreeError) as e:
            raise PluginError(f"docs: <!-- gen: {kind} {name} -->: {e}") from e

    return DIRECTIVE.sub(one, markdown)


# ---- which config a command reads


def commands(root: Path = ROOT) -> dict[str, str]:
    """``{console script: root config name}`` of every console script in ``pyproject.toml``."""
    out = {}
    for name, module in tree_pages.commands(root).items():
        path = root / "src" / Path(*module.split(".")).with_suffix(".py")
        out[name] = command_config(path)
    return out


def command_config(path: Path) -> str:
    """The config name given to ``@graf_command("...")`` in the command module at ``path``."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "graf_command" and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                return arg.value
    raise ValueError(f'{path.relative_to(ROOT)}: no @graf_command("...") names the command\'s config')


# ---- a config file's keys and comments


def keyed_rows(text: str) -> tuple[str, list[tuple[str, str, str]], list]:
    """A YAML file's header comment, its settings as ``(dotted key, default as written, comment)`` rows, and its
    ``defaults`` list (as data)."""
    lines = text.splitlines()
    root = yaml.compose(text)
    if root is None:
        return header(lines), [], []
    if not isinstance(root, yaml.MappingNode):
        raise ValueError("not a mapping of settings")
    rows: list[tuple[str, str, str]] = []
    defaults = []
    for key, value in root.value:
        if key.value == "defaults":
            defaults = yaml.safe_load(text).get("defaults") or []
            continue
        walk(key, value, "", lines, text, rows)
    return header(lines), rows, defaults


def walk(key, value, prefix: str, lines: list[str], text: str, rows: list) -> None:
    """Rows of one key: a nested block of settings key by key, anything else as one row."""
    name = prefix + str(key.value)
    comment = comment_of(key, value, lines)
    if isinstance(value, yaml.MappingNode) and not value.flow_style and value.value:
        children = value.value
        if all(isinstance(v, yaml.MappingNode) for _, v in children):  # named entries: one row
            names = ", ".join(f"`{k.value}`" for k, _ in children)
            rows.append((name, f"entries: {names}", comment))
            return
        if comment:
            rows.append((name, "", comment))
        for k, v in children:
            walk(k, v, name + ".", lines, text, rows)
        return
    if isinstance(value, yaml.SequenceNode) and value.value and isinstance(value.value[0], yaml.MappingNode):
        rows.append((name, f"a list of {len(value.value)} entries", comment))
        return
    rows.append((name, written(text[value.start_mark.index : value.end_mark.index]), comment))


def written(source: str) -> str:
    """A default as the file writes it, on one line; an environment lookup and a mandatory value in words."""
    s = " ".join(source.split())
    env = re.fullmatch(r"\$\{oc\.env:(\w+),(.*)\}", s)
    if env:
        return f"`{env.group(2)}` (or `${env.group(1)}`)"
    if s == "???":
        return "required"
    if not s:
        return "`null`"
    return f"`{s if len(s) <= 70 else s[:67] + '...'}`"


def comment_of(key, value, lines: list[str]) -> str:
    """The comment on the key's line (with the comment lines aligned under it), else the comment lines above it."""
    row = key.start_mark.line
    line = lines[row]
    end = value.end_mark.line if value.end_mark.line == row else row
    col = trailing_hash(line, value.end_mark.column if end == row else len(key.value) + key.start_mark.column + 1)
    if col is not None:
        parts = [line[col + 1 :].strip()]
        for nxt in lines[row + 1 :]:
            if nxt.strip().startswith("#") and len(nxt) - len(nxt.lstrip()) == col:
                parts.append(nxt.strip()[1:].strip())
            else:
                break
        return " ".join(parts)
    above = []
    for prev in reversed(lines[header_length(lines) : row]):
        s = prev.strip()
        if not s.startswith("#") or len(prev) - len(prev.lstrip()) != key.start_mark.column:
            break
        above.append(s[1:].strip())
    return " ".join(reversed([a for a in above if not a.startswith("@package")]))


def trailing_hash(line: str, start: int) -> int | None:
    """The column of the comment that ends ``line`` after column ``start`` (outside quotes), if any."""
    quote = None
    for i in range(start, len(line)):
        ch = line[i]
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return i
    return None


def header(lines: list[str]) -> str:
    """The file's opening comment up to its first blank comment line or indented example, without Hydra's
    ``@package`` line."""
    out = []
    for line in lines:
        s = line.strip()
        if not s.startswith("#") or line.startswith("#   "):
            break
        text = s[1:].strip()
        if not text:
            break
        if not text.startswith("@package"):
            out.append(text)
    return " ".join(out)


def header_length(lines: list[str]) -> int:
    """How many lines the file's opening comment takes (they describe the file, not its first key)."""
    n = 0
    while n < len(lines) and lines[n].strip().startswith("#"):
        n += 1
    return n


# ---- markdown


def cell(text: str) -> str:
    """Text for a table cell: ``|`` escaped, and outside code spans ``<`` and ``*`` (a ``<band>`` would be read as an
    HTML tag, a ``*`` as emphasis)."""
    parts = text.replace("|", "\\|").split("`")
    for i in range(0, len(parts), 2):  # outside backticks
        parts[i] = parts[i].replace("<", "&lt;").replace("*", "\\*")
    return "`".join(parts)


MACHINE = re.compile(r"\b\d[\d.,]* ?(?:ms|s|min|minutes|h)\b.*\bhere\b|\b\d+-core\b")  # a timing "here", a machine


def site_voice(text: str) -> str:
    """A comment without its asides about the machine it was measured on: a parenthesis's ``;``-separated parts that
    give a timing "here" or name an N-core machine (``(about 80 s here)``, ``1024 was fastest on the 2-core CPU``)
    are left out, as is a parenthesis left empty.  The site names machines and timings only in its Reproducibility
    log."""

    def keep(m: re.Match) -> str:
        parts = [p for p in m.group(1).split("; ") if not MACHINE.search(p)]
        return f" ({'; '.join(parts)})" if parts else ""

    return re.sub(r"\s*\(([^()]*)\)", keep, text)


def table(rows: list[tuple[str, str, str]]) -> str:
    body = [
        f"| `{key}` | {default} | {cell(site_voice(comment) or BUILT_IN.get(key, ''))} |"
        for key, default, comment in rows
    ]
    return "\n".join(["| key | default | what it sets |", "|---|---|---|", *body])


def config_block(name: str, depth: int) -> str:
    """The table of a command's root config (``graf-train``) or of a config file (``data/default.yaml``)."""
    if name.startswith("graf-"):
        known = commands()
        if name not in known:
            raise ValueError(f"no console script {name} in pyproject.toml")
        rel = f"{known[name]}.yaml"
    else:
        rel = name
    path = CONF / rel
    _, rows, defaults = keyed_rows(path.read_text())
    parts = []
    groups = [d for d in defaults if isinstance(d, dict)]
    if groups:
        up = "../" * depth
        items = []
        for d in groups:
            ((group, option),) = d.items()
            base = group.split("@")[0].removeprefix("override /")
            shown = "none" if option is None else f"`{option}`"
            anchor = base.replace("/", "") if (CONF / base).is_dir() and base != "hydra" else None
            link = f"[`{group}`]({up}configuration.md#{anchor})" if anchor else f"`{group}`"
            items.append(f"{link}: {shown}")
        parts.append("Config groups it composes (default option; `group=option` picks another):\n\n" + ", ".join(items))
    parts.append(table(rows) if rows else "(no settings of its own)")
    parts.append(f"*Generated from `src/graf/conf/{rel}`; override any key with `key=value`.*")
    return "\n\n".join(parts)


def group_block(group: str) -> str:
    """The options of config group ``group``: each file's name and the first sentence of its comment."""
    folder = CONF / group
    if not folder.is_dir():
        raise ValueError(f"no config group {group} under src/graf/conf")
    rows = []
    for path in sorted(folder.rglob("*.yaml")):
        rel = path.relative_to(folder)
        if rel.parts[0] == "base":
            continue
        option = rel.with_suffix("").as_posix()
        rows.append(f"| `{option}` | {cell(site_voice(first_sentence(header(path.read_text().splitlines()))))} |")
    body = "\n".join(["| option | what it is |", "|---|---|", *rows])
    return body + f"\n\n*Generated from `src/graf/conf/{group}/`.*"


def first_sentence(text: str) -> str:
    """Up to the first full stop that ends a sentence (not one inside a file name, a number or "e.g.")."""
    m = re.search(r"(?<!e\.g)(?<!i\.e)\.(\s|$)", text)
    return text[: m.start() + 1] if m else text


# ---- the interpolation case study (graf-interp's records)

INTERP_SCALES = (0.01, 0.1, 1.0, 5.0)  # the fine scales shown, in wavelengths


def interp_table(paths: str) -> str:
    """Two tables of the graf-interp records in ``paths`` (comma-separated folders under the repository): per scene
    the dataset part's slopes and the fine scales' median error and steepest local slope (a scene once, from the
    first record that has it); per record and scene, error / dP^2 against the curvature K."""
    scales = " / ".join(f"{w:g}" for w in INTERP_SCALES)
    first = [["scene", "dataset slope, barycentric [95%]", "dataset slope, IDW",
              f"median RMSE at ΔP = {scales} wavelengths", "steepest local slope (at ΔP)"]]  # fmt: skip
    second = [["record", "scene", "K step = scale", "Spearman ρ (K, error/ΔP²) (p)", "slope of error/ΔP² on K [95%]"]]
    seen = set()
    for rel in paths.split(","):
        record = json.loads((ROOT / rel / "results.json").read_text())
        for scene, r in record["scenes"].items():
            if scene not in seen:
                seen.add(scene)
                first.append([scene, *interp_row(r)])
            if r.get("curvature"):
                second.append([f"`{Path(rel).name}`", scene, *curvature_row(r["curvature"])])
    names = ", ".join(f"`{p}/results.json`" for p in paths.split(","))
    return "\n\n".join([markdown(first), markdown(second), f"*Generated from {names}.*"])


def markdown(rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0]),
                      *["| " + " | ".join(r) + " |" for r in rows[1:]]])  # fmt: skip


def interp_row(r: dict) -> list[str]:
    """The dataset part's slopes and the fine scales' figures of one scene (a measured scene: the dataset part)."""
    bary, idw = r["dataset"]["barycentric"]["fit"], r["dataset"]["idw"]["fit"]
    out = [f"{bary['slope']:.2f} [{bary['ci'][0]:.2f}, {bary['ci'][1]:.2f}]", f"{idw['slope']:.2f}"]
    fine = r.get("fine")
    if not fine:
        return out + ["-", "-"]
    scales = [x / r["wavelength_m"] for x in fine["scales_m"]]
    med = fine["barycentric"]["median_rmse"]
    picks = [min(range(len(scales)), key=lambda i, w=w: abs(scales[i] - w)) for w in INTERP_SCALES]
    local = fine["barycentric"]["local_slopes"]
    k = max(range(len(local["slope"])), key=lambda i: local["slope"][i])
    return out + [
        " / ".join(f"{med[i]:.2g}" for i in picks),
        f"{local['slope'][k]:.2f} ({local['at_m'][k] * 1000:.0f} mm)",
    ]


def curvature_row(c: dict) -> list[str]:
    """error / dP^2 against K at one scene: the step and scale, the rank correlation, the log-log slope."""
    fit = c["fit_ratio_vs_K"]
    step = (
        f"{c['fd_step_m'] * 1000:.1f} mm"
        if c["fd_step_m"] == c["scale_m"]
        else f"{c['fd_step_m'] * 1000:.1f} mm, {c['scale_m'] * 1000:.1f} mm"
    )
    return [
        step,
        f"{c['spearman_rho']:.2f} ({c['spearman_p']:.1g})",
        f"{fit['slope']:.2f} [{fit['ci'][0]:.2f}, {fit['ci'][1]:.2f}]",
    ]


def settings_table(name: str) -> str:
    """The table of ``hydra.sweeper``'s settings (key, default, meaning), read from their one home,
    :class:`graf.sweeper.settings.GrafOptunaSweeperConf`."""
    if name != "hydra.sweeper":
        raise ValueError(f"no settings class for {name}; hydra.sweeper is the one there is")
    from graf.sweeper.settings import settings_rows

    def shown(value) -> str:  # YAML's spelling, as on the command line (null, true, [test=true])
        return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()

    rows = [f"| `{key}` | `{shown(default)}` | {meaning} |" for key, default, meaning in settings_rows()]
    return (
        "| key | default | meaning |\n|---|---|---|\n"
        + "\n".join(rows)
        + ("\n\n*Generated from `graf.sweeper.settings.GrafOptunaSweeperConf`, the settings' one home.*")
    )
