"""A scene identified by its content, not its config name.

Two NeRF2 folders read through the same config (``scene=nerf2``) share a name but not their data; the same
data read under another name is the same scene.  What a checkpoint records about the scenes it was trained
on (``checkpoint["graf"]["scenes"]``) carries each one's fingerprint: digests of the gateway pose, the
transmitter positions (with their ids) and the spectra, and the band.  Whether a test scene was "seen" in
training, which scene index it gets, and which scene a fine-tuning run continues are decided by the
fingerprint (:func:`find_scene`); a checkpoint written before fingerprints falls back to the name.
"""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import torch

log = logging.getLogger(__name__)


def _sha(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def scene_fingerprint(data, frequency_hz: float) -> dict:
    """``{"digest", "gateway", "positions", "spectra", "band_hz", "n", "source"}`` of a :class:`SpectrumSet` at a
    band (sha256 hex digests; ``digest`` joins the others).  The content digests are computed once per set.
    ``source`` (where the set was read from) is no part of its identity: a message names it when two scenes of
    one name differ (:func:`differences`)."""
    parts = getattr(data, "_content_digests", None)
    if parts is None:
        parts = {
            "gateway": _sha(
                np.asarray(data.gateway_position, np.float64), np.asarray(data.gateway_orientation, np.float64)
            ),
            "positions": _sha(np.asarray(data.ids, np.int64), np.asarray(data.positions, np.float64)),
            "spectra": _sha(torch.as_tensor(data.spectra, dtype=torch.float32)),
        }
        data._content_digests = parts
    band_hz = float(frequency_hz)
    digest = hashlib.sha256(f"{parts['gateway']}|{parts['positions']}|{parts['spectra']}|{band_hz:.6f}".encode())
    out = {"digest": digest.hexdigest(), **parts, "band_hz": band_hz, "n": int(len(data.ids))}
    return {**out, "source": str(data.source)} if getattr(data, "source", None) else out


PARTS = {"gateway": "gateway pose", "positions": "transmitter positions", "spectra": "spectra", "band_hz": "band"}


def describe(fingerprint: dict) -> str:
    """A scene as a message names it: ``/data/a (content fingerprint 3f2a9c1b04de, 480 spectra)``."""
    where = fingerprint.get("source") or "a folder the checkpoint does not record"
    return f"{where} (content fingerprint {str(fingerprint.get('digest'))[:12]}, {fingerprint.get('n')} spectra)"


def differences(a: dict, b: dict) -> str:
    """What differs between two fingerprints, in words: ``its transmitter positions and spectra differ``."""
    parts = [words for key, words in PARTS.items() if a.get(key) != b.get(key) and a.get(key) and b.get(key)]
    return f"its {' and '.join(parts)} differ" if parts else "its content differs"


def find_scene(table: dict, name: str, fingerprint: dict) -> str | None:
    """The key in ``table`` (``{key: {"index", "band_hz", "fingerprint"?}}``) of the scene with this content, or
    None when the model never saw it.  Entries without a fingerprint (checkpoints written before them) match by
    name."""
    for key, entry in table.items():
        fp = entry.get("fingerprint")
        if fp is not None and fp.get("digest") == fingerprint["digest"]:
            return key
    for key, entry in table.items():  # the same measurements, the gateway pose's digest apart
        fp = entry.get("fingerprint")
        if fp is not None and _same_measurements(fp, fingerprint):
            log.info(
                "scene %s: the same transmitter positions, spectra and band as the checkpoint's %s, but not the "
                "same gateway-pose digest (its normalised quaternion rounded differently where the checkpoint was "
                "made: another numpy or BLAS): taken as the same scene",
                name,
                key,
            )
            return key
    if name in table and table[name].get("fingerprint") is None:
        log.warning(
            "scene %s: the checkpoint records no fingerprint for it (written before they were kept): "
            "taken as the same scene by its name alone",
            name,
        )
        return name
    return None


def _same_measurements(a: dict, b: dict) -> bool:
    """Same transmitter positions (with ids), same spectra and same band: the same scene whatever the last bits
    of its gateway pose.  (The pose is normalised in floating point, and a checkpoint made before the reader's
    norm became a correctly rounded sum may carry another rounding of it.)"""
    return (
        bool(a.get("positions"))
        and a.get("positions") == b.get("positions")
        and a.get("spectra") == b.get("spectra")
        and abs(float(a.get("band_hz", -1.0)) - float(b.get("band_hz", -2.0))) < 1e-3
    )


def register_scene(table: dict, name: str, fingerprint: dict, index: int) -> str:
    """Add a scene to ``table`` unless its content is there already; returns its key (the name, or
    ``name#<digest[:8]>`` when another scene of that name is there)."""
    key = find_scene(table, name, fingerprint)
    if key is not None:
        return key
    key = name if name not in table else f"{name}#{fingerprint['digest'][:8]}"
    table[key] = {"index": int(index), "band_hz": float(fingerprint["band_hz"]), "fingerprint": fingerprint}
    return key


def next_index(table: dict) -> int:
    return max((int(v["index"]) for v in table.values()), default=-1) + 1


# how a test scene's index was decided (results.json ``scene_indices``)
TRAINED, SAME_PLACE, UNSEEN = "trained", "same place, another band", "unseen"


def eval_scene_index(table: dict, name: str, fingerprint: dict) -> tuple[int, str]:
    """The scene index a test scene gets from a model that knows the scenes of ``table``, and why:

    - ``trained``: the model was trained on this content: the index it was trained with;
    - ``same place, another band``: a trained scene of the same name, gateway pose and transmitter positions,
      measured at another band (the bands study): that scene's index, so a band transfer is not also an index
      change;
    - ``unseen``: any other scene gets one fixed index, the first the model was not trained with
      (:func:`next_index`), whatever else is tested beside it and in whatever order: a zero-shot prediction
      depends on the scene, never on its place in a list.
    """
    key = find_scene(table, name, fingerprint)
    if key is not None:
        return int(table[key]["index"]), TRAINED
    for key, entry in table.items():
        fp = entry.get("fingerprint")
        if (
            key.split("#")[0] == name
            and fp is not None
            and fp.get("positions") == fingerprint.get("positions")
            and fp.get("gateway") == fingerprint.get("gateway")
        ):
            return int(entry["index"]), SAME_PLACE
    return next_index(table), UNSEEN
