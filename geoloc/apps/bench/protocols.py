"""The test protocols of a row: the street view's field of view, with the heading known (the view at north) or
unknown (searched over candidate headings). Published FoV figures differ by about 3x between the two, so every row
names its protocol."""

from __future__ import annotations

from dataclasses import dataclass

from geoloc.apps.robustness.conditions import test_condition

HEADINGS = ("known", "unknown")


@dataclass(frozen=True)
class Protocol:
    fov: float
    heading: str  # "known" | "unknown"
    heading_steps: int = 12

    @property
    def name(self) -> str:
        unknown = f"unknown ({self.heading_steps} steps)" if self.heading == "unknown" else "known"
        return f"FoV {self.fov:g}, heading {unknown}"

    def overrides(self) -> tuple[str, ...]:
        """evaluate.py's overrides for this protocol (the robustness table's, test_condition)."""
        return test_condition(self.fov, self.heading == "unknown", self.heading_steps)


def protocols(fovs: list[float], headings: list[str], heading_steps: int) -> list[Protocol]:
    """Each FoV with each heading, in that order."""
    return [Protocol(float(fov), heading, heading_steps) for fov in fovs for heading in headings]


PHOTO = Protocol(360.0, "known")  # the one protocol of photo queries (University-1652's drone views and tiles)
