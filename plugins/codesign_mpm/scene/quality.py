"""Quality presets: one name for the numerical settings that trade accuracy for time.

`quality: draft | default | paper | reference` in an environment's recipe config (or a scene
file) sets the grid spacing, particles per cell (the robot's and the cover's), CFL number,
precision and checkpoint interval at once; any of those keys written explicitly overrides the
preset. The values were chosen from the measured error-against-time fronts of `codesign bench
accuracy` (docs/accuracy.md, whose preset table is generated from this constant and checked
against it by a test).

Light on purpose: recipe validation imports it without Taichi.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional


@dataclass(frozen=True)
class Quality:
    dx: float
    particles_per_cell: int  # the robot's (and any body's but a cover layer)
    cover_particles_per_cell: int  # the ground cover's (sand, water, snow ...): a cover layer's
    cfl: float
    dtype: str
    checkpoint_every: Optional[int] = None  # substeps between stored states; None: engine's default_segment
    purpose: str = ""

    def settings(self) -> dict:
        """The settings a preset sets (its purpose left out)."""
        return {k: v for k, v in asdict(self).items() if k != "purpose"}


QUALITY: dict[str, Quality] = {
    "draft": Quality(dx=1 / 32, particles_per_cell=8, cover_particles_per_cell=8, cfl=0.4, dtype="float32",
                     purpose="smoke tests, recipe debugging, quick sweeps (the quick start's grid); cfl 0.8 "
                             "blows up far earlier in docs/stability.md. A gait's distance from rest is a quarter "
                             "off and fast gaits move differently; it ranks 24 random gaits roughly as paper does "
                             "(Spearman 0.79 on ground, 0.80 in sand, docs/log/contact.md section 23): not for final "
                             "rankings; in the desert a third under the reference (its 0.02 of sand is 0.64 cells "
                             "thick)"),
    "default": Quality(dx=1 / 48, particles_per_cell=8, cover_particles_per_cell=8, cfl=0.4, dtype="float32",
                       purpose="day-to-day optimisation at one fixed setting. A gait's distance from rest within "
                               "8% of the reference (the terrain's offset within a cell moves it +-15%), gaits "
                               "ranked as paper ranks them (Spearman 0.90 over 24 random gaits, docs/log/contact.md "
                               "section 23); from a stress-free start (design optimisation) a third off: confirm a "
                               "number at paper. In the desert within 6% (the offset +-6%), gaits ranked as paper "
                               "ranks them (Spearman 0.92 over 24; gaits that move under a millimetre swap)"),
    "paper": Quality(dx=1 / 96, particles_per_cell=8, cover_particles_per_cell=27, cfl=0.4, dtype="float32",
                     purpose="figures and final numbers: a gait's distance from rest within 8% of the reference "
                             "and 2% of dx 1/160, the terrain's offset within a cell moving it +-4% "
                             "(docs/log/contact.md section 17); from a stress-free start the offset moves it about "
                             "15% (section 13): compare designs on one terrain, or set terrain.contact: surface "
                             "with cfl 0.2 (section 15). In the desert 8% over the reference (the offset +-5%) "
                             "with the cover at 27 particles per cell (at 8 it was 15% over; section 21), which "
                             "costs 3x the sand's particles and 3.4x the ocean's water (1.5 M particles; its swim "
                             "moved 4 to 7% between 8 and 27 at dx 1/48, section 22); set "
                             "cover.particles_per_cell: 8 to save it"),
    "reference": Quality(dx=1 / 128, particles_per_cell=27, cover_particles_per_cell=27, cfl=0.2, dtype="float64",
                         purpose="the finest setting measured: the answer the others are compared with. On ground from "
                                 "rest it agrees with dx 1/160 within 6% (docs/log/contact.md section 17), from a "
                                 "stress-free start it has no limit (section 13); in the desert it agrees with dx "
                                 "1/96 at its setting within 2% (section 21)"),
}
QUALITY_NAMES = tuple(QUALITY)


def quality(name: str, key: str = "environment.quality") -> Quality:
    """The preset called `name`; a `RecipeError` naming `key` and the allowed names otherwise."""
    if name not in QUALITY:
        from codesign.errors import RecipeError
        from codesign.registry import suggest

        raise RecipeError(f"invalid recipe: {key}: {name!r} is not a quality preset; "
                          f"{suggest(str(name), QUALITY)}allowed: {', '.join(QUALITY)}")
    return QUALITY[name]
