"""A command line's overrides before Hydra sees them: old spellings brought up to date (with a warning), and the
mistakes Hydra would report as a page (an unknown option of a config group, ``+key=`` on a key that exists, a
key that does not exist, a path with a non-ASCII character left unquoted) refused in one line
(:class:`graf.errors.ConfigError`), with the quoted form to write for the last.  Used by
:func:`graf.cli.entry.graf_command`."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ValueType
from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException

from graf.app.config import CONF_DIR
from graf.errors import ConfigError
from graf.plugins import CONF_DIRS

__all__ = ["RENAMED_KEYS", "check_overrides", "modernize"]

# Settings that became something else: the old key (after "neighbour" -> "neighbor") -> the new key.  A new key
# with "/" is a config group; an entry applies only once its group exists in the config folder.
RENAMED_KEYS: dict[str, str] = {
    "model.neighbor_features": "model/features",
}
# Options of a config group that were renamed (the old name builds the same thing, with a one-line deprecation):
# presets are named for the neighbor-feature mode they build.
RENAMED_OPTIONS: dict[str, dict[str, str]] = {
    "model": {"graf_cpu_ray": "graf_cpu_ray_weights", "graf_cpu_scenes_ray": "graf_cpu_scenes_ray_weights"},
}


def split_key(arg: str) -> tuple[str, str, str]:
    """``+model.lr@pkg=0.1`` -> (``+``, ``model.lr@pkg``, ``0.1``): the prefix, the key and the value."""
    key, _, value = arg.partition("=")
    bare = key.lstrip("+~")
    return key[: len(key) - len(bare)], bare, value


def is_group(key: str, conf_dir: Path = CONF_DIR) -> bool:
    """A config group of graf's (a folder of the config folder), e.g. ``band``, ``model/features``."""
    name = key.split("@", 1)[0]
    return bool(name) and "." not in name and (conf_dir / name).is_dir()


def modernize(args: list[str], conf_dir: Path = CONF_DIR) -> tuple[list[str], list[str]]:
    """The overrides in today's spelling, and one deprecation warning per override changed: "neighbour" ->
    "neighbor" in any key and in a config group's value (``experiment=neighbour_count``), then
    :data:`RENAMED_KEYS` (``model.neighbour_features=X`` -> ``model/features=X``) and :data:`RENAMED_OPTIONS`
    (``model=graf_cpu_scenes_ray`` -> ``model=graf_cpu_scenes_ray_weights``).  Flags (``-m``) pass as
    they are."""
    out, warnings = [], []
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            out.append(arg)
            continue
        prefix, key, value = split_key(arg)
        key = key.replace("neighbour", "neighbor")
        renamed = RENAMED_KEYS.get(key)
        if renamed and is_group(renamed, conf_dir):
            key = renamed
        if is_group(key, conf_dir):
            value = value.replace("neighbour", "neighbor")
            for was, now in RENAMED_OPTIONS.get(key.split("@", 1)[0], {}).items():  # each item of a sweep or list
                value = re.sub(rf"(?<![\w/]){was}(?![\w])", now, value)
        new = f"{prefix}{key}={value}"
        if new != arg:
            warnings.append(f"warning: '{arg}' is deprecated; write '{new}'")
        out.append(new)
    return out, warnings


def options(group: str, conf_dir: Path = CONF_DIR) -> list[str]:
    """The options of a config group: its files' names (``band`` -> ``1.8ghz``, ``2.4ghz``, ...)."""
    return sorted(p.stem for p in (conf_dir / group).glob("*.yaml"))


def unknown_option(group: str, value: str, choices) -> ConfigError:
    return ConfigError(f"{group}={value}: no such option of '{group}'; the options are {', '.join(choices)}")


def group_values(override) -> list[str]:
    """The options a config-group override names: each value of a sweep, each item of a list (``scene=[a,b]``); none
    for a glob (``experiment=glob(compare_*)``), which only Hydra's config loader can expand: it checks those."""
    if override.value_type == ValueType.GLOB_CHOICE_SWEEP:
        return []
    given = override.sweep_string_iterator() if override.is_sweep_override() else [override.get_value_element_as_str()]
    out = []
    for value in given:
        listed = value.startswith("[") and value.endswith("]")
        out += [v.strip() for v in value[1:-1].split(",") if v.strip()] if listed else [value]
    return out


def searchpath_dirs(overrides) -> list[Path]:
    """The config folders a ``hydra.searchpath=[file://DIR, ...]`` override adds (a plugin's configs: a method's
    ``model/<name>.yaml``, docs/extending.md); ``pkg://`` entries are left to Hydra."""
    dirs = []
    for o in overrides:
        if o.key_or_group == "hydra.searchpath" and not o.is_delete():
            for value in (v.replace("\\:", ":").strip("'\"") for v in group_values(o)):  # file\:// as Hydra quotes it
                if value.startswith("file://"):
                    dirs.append(Path(value[len("file://") :]))
    return dirs


def check_group_values(overrides) -> None:
    """Every value of a graf config group given on the command line (each value of a sweep) is one of its files,
    in graf's config folder, a plugin's (:func:`graf.plugins.add_conf`) or one a ``hydra.searchpath`` override
    adds."""
    dirs = [CONF_DIR, *CONF_DIRS, *searchpath_dirs(overrides)]
    for o in overrides:
        group = o.key_or_group
        if o.is_delete() or group.startswith("hydra/") or not is_group(group):
            continue
        for value in group_values(o):  # an option in a subfolder of the group (experiment=base/x) is a file too
            if value != "null" and not any((d / group / f"{value}.yaml").is_file() for d in dirs):
                raise unknown_option(group, value, sorted({o for d in dirs for o in options(group, d)}))


def first_job(overrides) -> list[str]:
    """The overrides of a sweep's first job (each sweep at its first value), to compose one config."""
    out = []
    for o in overrides:
        if o.is_sweep_override():
            out.append(f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}")
        else:
            out.append(o.input_line)
    return out


def composition_error(exc: ConfigCompositionException, args: list[str]) -> ConfigError:
    """Hydra's composition error (a few lines) as one line."""
    if isinstance(exc, MissingConfigException) and exc.missing_cfg_file and "/" in exc.missing_cfg_file:
        group, _, value = exc.missing_cfg_file.rpartition("/")
        return unknown_option(group, value, exc.options or [])
    text = str(exc)
    if "An item is already at" in text:
        key = text.split("An item is already at '", 1)[1].split("'", 1)[0]
        given = next((a for a in args if split_key(a)[1] == key and a.startswith("+")), f"+{key}")
        return ConfigError(f"{given}: {key} is already set; drop the '+' ({given.lstrip('+')})")
    if text.startswith("Could not override '") and "not in struct" in str(exc.__cause__):
        key = text.split("'", 2)[1]
        given = next((a for a in args if split_key(a)[1] == key), key)
        return ConfigError(f"{given}: no such setting (to add one, write +{given.lstrip('+')})")
    cause = f" ({exc.__cause__})" if exc.__cause__ is not None else ""
    return ConfigError(" ".join((text + cause).split()))


def quoted(arg: str) -> str | None:
    """The override with its value (each value of a sweep ``a,b``) in quotes, when Hydra's grammar reads that; None
    when it does not, or when the value is quoted or a list or mapping already."""
    prefix, key, value = split_key(arg)
    if not value or value[0] in "\"'[{":
        return None
    items = [v if v[:1] in "\"'" else (f'"{v}"' if '"' not in v else f"'{v}'") for v in value.split(",")]
    fixed = f"{prefix}{key}={','.join(items)}"
    try:
        OverridesParser.create().parse_overrides([fixed])
    except OverrideParseException:
        return None
    return fixed


def parse_error(exc: OverrideParseException) -> ConfigError:
    """Hydra's syntax error as one line; for a value that Hydra reads only quoted (a path with a non-ASCII
    character, ``data_root=/tmp/dätä``: ``LexerNoViableAltException`` and nothing more), the quoted form to write,
    quoted for the shell as well."""
    fixed = quoted(exc.override)
    if fixed is None:
        return ConfigError(f"{exc.override}: {exc.message.splitlines()[0]}")
    what = "a value with non-ASCII characters" if not exc.override.isascii() else "this value"
    return ConfigError(f"{exc.override}: Hydra reads {what} only in quotes: write {shlex.quote(fixed)}")


def check_overrides(config_name: str, args: list[str]) -> None:
    """Refuse, with one line (:class:`ConfigError`), the overrides that Hydra would refuse with a page: a syntax
    error, an unknown option of a config group, and anything else the first job's config cannot be composed
    with (``+key=`` on a key that exists, a key that does not)."""
    try:
        overrides = OverridesParser.create().parse_overrides(args)
    except OverrideParseException as exc:
        raise parse_error(exc) from exc
    check_group_values(overrides)
    if searchpath_dirs(overrides):  # configs of the user's own folder: Hydra composes them itself
        return
    try:
        first = first_job(overrides)
    except Exception:  # a sweep that needs Hydra's config loader (glob): Hydra checks it itself
        return
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            compose(config_name=config_name, overrides=first)
    except ConfigCompositionException as exc:
        raise composition_error(exc, args) from exc
