"""Radio materials from ITU-R P.2040 (the table Sionna RT ships), evaluated at the scene's band.

eps_r = a f^b, sigma = c f^d with f in GHz.  Where a band lies outside every range the table gives for
a material (e.g. concrete below 1 GHz, for the 915 MHz band), the nearest range's law is extrapolated
and the dataset records it (``extrapolated: true``) -- Sionna's own ITURadioMaterial refuses such bands.
"""

from __future__ import annotations


def itu_parameters(itu_type: str, frequency_hz: float) -> dict:
    # lazy: Sionna RT (Dr.Jit, Mitsuba) takes seconds to load and needs graf.sim's LLVM set-up first
    from sionna.rt.radio_materials.itu import ITU_MATERIALS_PROPERTIES

    if itu_type not in ITU_MATERIALS_PROPERTIES:
        raise ValueError(f"unknown ITU material {itu_type!r}; known: {sorted(ITU_MATERIALS_PROPERTIES)}")
    f = frequency_hz / 1e9
    ranges = ITU_MATERIALS_PROPERTIES[itu_type]
    inside = [(r, p) for r, p in ranges.items() if r[0] <= f <= r[1]]
    if inside:
        (lo, hi), (a, b, c, d) = inside[0]
        extrapolated = False
    else:
        (lo, hi), (a, b, c, d) = min(ranges.items(), key=lambda kv: min(abs(f - kv[0][0]), abs(f - kv[0][1])))
        extrapolated = True
    return {
        "itu_type": itu_type,
        "relative_permittivity": a * f**b,
        "conductivity": c * f**d,
        "itu_range_ghz": [lo, hi],
        "extrapolated": extrapolated,
    }
