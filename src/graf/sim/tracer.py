"""Sionna RT tracing of every transmitter position to the gateway, and the paths -> channels step.

The positions are the sources (``Transmitter``s, ``sources_per_call`` at a time) and the gateway is
one receiver with a single isotropic antenna; the 4x4 array is applied afterwards from each path's
complex gain (``Paths.cir``, carrier phase included) and arrival direction, which is exact for plane
waves across the array (Sionna's synthetic arrays do the same).
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from graf.geometry.shapes import SceneGeometry
from graf.sim.array import Bartlett
from graf.sim.backend import import_sionna_rt
from graf.sim.materials import itu_parameters

log = logging.getLogger(__name__)

TRACING_KEYS = (
    "max_depth",
    "los",
    "specular_reflection",
    "diffuse_reflection",
    "refraction",
    "diffraction",
    "edge_diffraction",
    "samples_per_src",
    "max_num_paths_per_src",
    "seed",
)


class SionnaTracer:
    """Builds the Sionna scene once; :meth:`trace` returns path gains and gateway-frame directions."""

    def __init__(
        self,
        geometry: SceneGeometry,
        frequency_hz: float,
        gateway_position,
        gateway_rotation,
        tracing: dict,
        sources_per_call: int = 256,
    ):
        rt = import_sionna_rt()
        import mitsuba as mi  # lazy, after Sionna RT (which sets up Dr.Jit's LLVM backend): seconds to load

        self.rt, self.mi = rt, mi
        self.tracing = {k: tracing[k] for k in TRACING_KEYS if k in tracing}
        self.sources_per_call = int(sources_per_call)
        self.R = np.asarray(gateway_rotation.as_matrix(), float)  # local -> world
        self.materials: dict[tuple, dict] = {}
        scene = rt.load_scene()  # empty
        scene.frequency = float(frequency_hz)
        objs = []
        for s in geometry.surfaces:
            key = (s.material, round(s.thickness, 6))
            if key not in self.materials:
                p = itu_parameters(s.material, frequency_hz)
                name = f"{s.material}_{len(self.materials)}"
                mat = rt.RadioMaterial(
                    name=name,
                    thickness=s.thickness,
                    relative_permittivity=p["relative_permittivity"],
                    conductivity=p["conductivity"],
                )
                self.materials[key] = {"material": mat, **p, "thickness": s.thickness}
            mesh = mi.Mesh(s.name, len(s.vertices), len(s.faces), has_vertex_normals=False, has_vertex_texcoords=False)
            params = mi.traverse(mesh)
            params["vertex_positions"] = mi.Float(np.asarray(s.vertices, np.float32).ravel())
            params["faces"] = mi.UInt32(np.asarray(s.faces, np.uint32).ravel())
            params.update()
            objs.append(rt.SceneObject(mi_mesh=mesh, name=s.name, radio_material=self.materials[key]["material"]))
        if objs:
            scene.edit(add=objs)
        iso = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
        scene.tx_array, scene.rx_array = iso, iso
        scene.add(rt.Receiver(name="gateway", position=mi.Point3f(*[float(v) for v in gateway_position])))
        self.scene = scene
        self._txs: list = []
        self.solver = rt.PathSolver(deterministic=True)

    def material_table(self) -> list[dict]:
        return [{k: v for k, v in m.items() if k != "material"} for m in self.materials.values()]

    def _set_sources(self, positions: np.ndarray) -> None:
        mi, rt = self.mi, self.rt
        while len(self._txs) > len(positions):
            self.scene.remove(self._txs.pop().name)
        for i, p in enumerate(positions):
            pt = mi.Point3f(*[float(v) for v in p])
            if i < len(self._txs):
                self._txs[i].position = pt
            else:
                tx = rt.Transmitter(name=f"tx{i}", position=pt)
                self.scene.add(tx)
                self._txs.append(tx)

    def trace(self, positions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
        """For ``[n, 3]`` positions: complex gains ``[n, P]`` (0 where no path), arrival directions ``[n, P, 3]``
        in the gateway frame, and the number of valid paths per position ``[n]``."""
        gains, dirs, counts = [], [], []
        for start in range(0, len(positions), self.sources_per_call):
            chunk = positions[start : start + self.sources_per_call]
            self._set_sources(chunk)
            paths = self.solver(self.scene, synthetic_array=True, **self.tracing)
            a, _ = paths.cir(normalize_delays=False, out_type="numpy")  # [rx, rx_ant, tx, tx_ant, P, 1]
            a = np.asarray(a)[0, 0, :, 0, :, 0]  # [n, P]
            valid = np.asarray(paths.valid.numpy()).reshape(len(chunk), -1).astype(bool)
            theta = np.asarray(paths.theta_r.numpy()).reshape(len(chunk), -1)
            phi = np.asarray(paths.phi_r.numpy()).reshape(len(chunk), -1)
            u = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
            a = np.where(valid, a, 0)
            gains.append(a)
            dirs.append(u @ self.R)  # world -> gateway frame (R^T u)
            counts.append(valid.sum(1))
        P = max(g.shape[1] for g in gains)
        pad = lambda x, w: np.pad(x, [(0, 0), (0, P - x.shape[1])] + [(0, 0)] * (x.ndim - 2))  # noqa: E731
        g = np.concatenate([pad(x, 0) for x in gains])
        d = np.concatenate([pad(x, 0) for x in dirs])
        return torch.from_numpy(g.astype(np.complex128)), torch.from_numpy(d.astype(np.float64)), np.concatenate(counts)


def spectra_from_paths(bartlett: Bartlett, gains, dirs, pattern: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Channels ``[n, K]`` and float spectra ``[n, 90, 360]`` from traced paths."""
    h = bartlett.channels(gains, dirs, pattern)
    return h, bartlett.spectra(h)
