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
        held = {param}
        for node in ast.walk(fn):  # names assigned from a call that took the config hold it too
            if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
                if any(carries(a, held) for a in node.value.args):
                    held |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        for node in ast.walk(fn):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get":
                if (
                    node.args
                    and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value in ("scene", "eval_scene")
                ):
                    readers.add(f"{mod}:{name}")
            if not isinstance(node, ast.Call):
                continue
            callee = node.func.id if isinstance(node.func, ast.Name) else None
            if callee is None and isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name):
                callee = f"{node.func.value.id}.{node.func.attr}"
            if callee is None:
                continue
            if callee in funcs[mod]:
                target = (mod, callee)
            elif callee in imports[mod]:
                target = imports[mod][callee]
            elif "." in callee and callee.split(".")[0] in imports[mod]:  # a class's classmethod: RunSpec.of
                m, cls = imports[mod][callee.split(".")[0]]
                target = (m, f"{cls}.{callee.split('.')[1]}")
            else:
                continue
            positions = [i for i, a in enumerate(node.args) if carries(a, held)]
            keywords = [k.arg for k in node.keywords if k.arg and carries(k.value, held)]
            if not positions and not keywords:
                continue
            cfn = funcs.get(target[0], {}).get(target[1])
            if cfn is None:
                continue
            params = [a.arg for a in cfn.args.args if a.arg not in ("self", "cls")]
            landed = [params[i] for i in positions if i < len(params)] + keywords
            if not landed:
                continue
            if target[0] == mod:
                counts["stays"] += 1
            else:
                counts["visits"] += 1
                visits[target[0]] += 1
                if target[0] in path:
                    counts["climbs"] += 1
            go(target[0], target[1], landed[0], path + (target[0],))

    m, f = start.split(":")
    fn = funcs[m][f]
    go(m, f, fn.args.args[0].arg, (m,))
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
