"""Walk a run's config through the package: from a function, follow every call that passes it on.

    python scripts/walk_config.py [graf.run.train:train] [--src src]

Read from the source (no import).  A call passes the config on when an argument is the parameter that holds it
(or that parameter's ``.cfg``, or a name assigned from a call that took it, such as ``spec = resolve_run(cfg)``);
the walk goes on into the callee with the parameter it lands in.  Each call is counted once per path as

- a stay: the callee is in the caller's module;
- a visit: the callee is in another module;
- a climb: the callee's module is already on the path (the walk returns up to a module it came through);

and the visits are tallied by module.  Prints the counts, the modules most visited, and each function that reads a
scene selection of the config (``.get("scene")``, ``["eval_scene"]``).  Issue 70 counted the walk from
``graf.run.train:train`` before and after the run spec (docs/layout.md).
"""

from __future__ import annotations

import argparse
import ast
from collections import Counter
from pathlib import Path


def modules(src: Path) -> dict[str, ast.Module]:
    out = {}
    for p in src.rglob("*.py"):
        parts = list(p.relative_to(src).with_suffix("").parts)
        if parts[0] != "graf" or "conf" in parts:
            continue
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = ast.parse(p.read_text())
    return out


def functions(tree: ast.Module) -> dict[str, ast.FunctionDef]:
    found = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            found[node.name] = node
        elif isinstance(node, ast.ClassDef):
            for sub in node.body:
                if isinstance(sub, ast.FunctionDef):
                    found[f"{node.name}.{sub.name}"] = sub
                    found.setdefault(sub.name, sub)
    return found


def imported(tree: ast.Module, mods: dict) -> dict[str, tuple[str, str]]:
    """Local name -> (module, function) for ``from graf.x import f``."""
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("graf"):
            for a in node.names:
                if node.module in mods:
                    names[a.asname or a.name] = (node.module, a.name)
    return names


def carries(arg: ast.expr, held: set[str]) -> bool:
    if isinstance(arg, ast.Name):
        return arg.id in held
    if isinstance(arg, ast.Attribute) and arg.attr == "cfg":
        return isinstance(arg.value, ast.Name) and arg.value.id in held
    return False


def holders(fn: ast.FunctionDef, param: str) -> set[str]:
    """The names in ``fn`` that hold the config: ``param``, and names assigned from a call that took it."""
    held = {param}
    for node in ast.walk(fn):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            if any(carries(a, held) for a in node.value.args):
                held |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return held


def reads_selection(fn: ast.FunctionDef) -> bool:
    """Whether ``fn`` reads a scene selection: ``.get("scene")`` or ``.get("eval_scene")``."""
    return any(
        isinstance(n, ast.Call)
        and isinstance(n.func, ast.Attribute)
        and n.func.attr == "get"
        and n.args
        and isinstance(n.args[0], ast.Constant)
        and n.args[0].value in ("scene", "eval_scene")
        for n in ast.walk(fn)
    )


def callee(node: ast.Call, mod: str, funcs: dict, imports: dict) -> tuple[str, str] | None:
    """(module, function) a call names: one of its module's, an imported one, or an imported class's method."""
    f = node.func
    name = f.id if isinstance(f, ast.Name) else None
    if name is None and isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name):
        name = f"{f.value.id}.{f.attr}"
    if name is None:
        return None
    if name in funcs[mod]:
        return mod, name
    if name in imports[mod]:
        return imports[mod][name]
    if "." in name and name.split(".")[0] in imports[mod]:  # a class's classmethod: RunSpec.of
        m, cls = imports[mod][name.split(".")[0]]
        return m, f"{cls}.{name.split('.')[1]}"
    return None


def landing(node: ast.Call, held: set[str], target_fn: ast.FunctionDef) -> str | None:
    """The parameter of ``target_fn`` the config lands in when ``node`` passes it (None: it is not passed)."""
    params = [a.arg for a in target_fn.args.args if a.arg not in ("self", "cls")]
    landed = [params[i] for i, a in enumerate(node.args) if carries(a, held) and i < len(params)]
    landed += [k.arg for k in node.keywords if k.arg and carries(k.value, held)]
    return landed[0] if landed else None


def walk(start: str, src: Path) -> dict:
    mods = modules(src)
    funcs = {m: functions(t) for m, t in mods.items()}
    imports = {m: imported(t, mods) for m, t in mods.items()}
    counts, visits, readers, seen = Counter(), Counter(), set(), set()

    def go(mod: str, name: str, param: str, path: tuple[str, ...]) -> None:
        fn = funcs.get(mod, {}).get(name)
        if fn is None or (mod, name, param) in seen:
            return
        seen.add((mod, name, param))
        if reads_selection(fn):
            readers.add(f"{mod}:{name}")
        held = holders(fn, param)
        for node in (n for n in ast.walk(fn) if isinstance(n, ast.Call)):
            target = callee(node, mod, funcs, imports)
            target_fn = funcs.get(target[0], {}).get(target[1]) if target else None
            into = landing(node, held, target_fn) if target_fn else None
            if into is None:
                continue
            kind = "stays" if target[0] == mod else "visits"
            counts[kind] += 1
            if kind == "visits":
                visits[target[0]] += 1
                counts["climbs"] += target[0] in path
            go(target[0], target[1], into, path + (target[0],))

    m, f = start.split(":")
    go(m, f, funcs[m][f].args.args[0].arg, (m,))
    return {"counts": counts, "visits": visits, "readers": sorted(readers), "functions": len(seen)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("start", nargs="?", default="graf.run.train:train")
    ap.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1] / "src")
    a = ap.parse_args()
    r = walk(a.start, a.src)
    c = r["counts"]
    print(
        f"{a.start}: {r['functions']} functions reached; {c['stays']} stays, {c['visits']} visits to other modules, "
        f"{c['climbs']} climbs back up"
    )
    print("most visited: " + ", ".join(f"{m} {n}" for m, n in r["visits"].most_common(6)))
    print("read a scene selection: " + (", ".join(r["readers"]) or "none"))


if __name__ == "__main__":
    main()
