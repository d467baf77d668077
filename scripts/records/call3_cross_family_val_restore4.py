"""Rebuild the carried slim catalog files under data/sim (sha256 checked against the traced originals)."""

from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from graf.sim.slim import restore


def one(f):
    scene, band = f.name.split(".slim.h5")[0].split("__")
    dst = Path("data/sim") / scene / f"{band}.h5"
    dst.parent.mkdir(parents=True, exist_ok=True)
    r = restore(f, dst)
    return scene, r["n"], r["match"]


if __name__ == "__main__":
    files = sorted(Path(".paper_gpu/catalog").glob("*.slim.h5"))
    with ProcessPoolExecutor(len(files)) as ex:
        for row in ex.map(one, files):
            print("restored", *row, flush=True)
