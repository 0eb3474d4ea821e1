"""The depth camera's and the tracker's options (:class:`CameraSpec`, :class:`TrackerSpec`):
torch- and scipy-free, for the observation spec (:mod:`dlocli.specs`) and the commands.

Camera defaults: an RGB-D camera on a tripod in front of the workspace, 1.7 rod lengths
from its centre, looking slightly down at it; 160 x 120 pixels at 25 frames per second
(every second control step), the resolution ``mj_multiRay`` casts in a few milliseconds
(benchmarks/results/tracking.txt). Depth noise grows with distance as a structured-light
sensor's axial noise does (Nguyen, Izadi and Lovell, 3DIMPVT 2012:
sigma(z) = 1.2 mm + 1.9 mm/m^2 (z - 0.4 m)^2).
"""

from __future__ import annotations

from pydantic import Field, model_validator

from dlocli.limits import MAX_CAMERA_PIXELS, MAX_TRACKER_NODES
from dlocli.spec_base import Spec

Vector = tuple[float, float, float]


class CameraSpec(Spec):
    """A simulated depth camera: pose, intrinsics, the sensor's faults and the colour
    segmentation's stray points."""

    width: int = Field(160, ge=1, le=4096, description="Image width in pixels.")
    height: int = Field(120, ge=1, le=4096, description="Image height in pixels.")
    fov_deg: float = Field(
        58.0, gt=0.0, lt=180.0,
        description="Vertical field of view (degrees); sets the focal length unless fx, fy do.",
    )  # fmt: skip
    fx: float | None = Field(None, description="Focal length along x in pixels (None: from fov).")
    fy: float | None = Field(None, description="Focal length along y in pixels (None: from fov).")
    cx: float | None = Field(None, description="Principal point x in pixels (None: the centre).")
    cy: float | None = Field(None, description="Principal point y in pixels (None: the centre).")
    position: Vector = Field(
        (0.0, -1.6, 1.1), description="Camera position in rod lengths, world frame (z up)."
    )
    look_at: Vector = Field(
        (0.0, 0.0, 0.6), description="The point the optical axis passes through (rod lengths)."
    )
    rate_hz: float = Field(25.0, gt=0.0, le=1000.0, description="Frames per second.")
    min_range: float = Field(0.2, ge=0.0, description="Nearest valid depth (m).")
    max_range: float = Field(4.0, gt=0.0, description="Farthest valid depth (m).")
    noise_mm: float = Field(
        1.2, ge=0.0, le=1000.0, description="Depth noise (standard deviation, mm) at 0.4 m."
    )
    noise_growth_mm: float = Field(
        1.9, ge=0.0, le=1000.0,
        description="Growth of the depth noise, mm per (m beyond 0.4 m) squared.",
    )  # fmt: skip
    invalid_fraction: float = Field(
        0.02, ge=0.0, lt=1.0, description="Fraction of pixels with no depth (dropped at random)."
    )
    stray_fraction: float = Field(
        0.02, ge=0.0, le=1.0,
        description="Stray points the colour segmentation adds, per cable point: pixels of "
        "the table or the grippers taken for cable.",
    )  # fmt: skip
    table_height: float | None = Field(
        0.0, description="Height of the table top in rod lengths (None: no table)."
    )
    see_grippers: bool = Field(
        True, description="Whether the grippers are in the view (they hide the cable's ends)."
    )

    @model_validator(mode="after")
    def _makes_an_image(self) -> CameraSpec:
        if self.width * self.height > MAX_CAMERA_PIXELS:
            raise ValueError(
                f"width x height is {self.width} x {self.height} = {self.width * self.height:,} "
                f"pixels, more than the {MAX_CAMERA_PIXELS:,} (1920 x 1080) a camera may have; "
                "lower camera.width or camera.height"
            )
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be a positive focal length in pixels")
        for name, size in (("cx", self.width), ("cy", self.height)):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= size:
                raise ValueError(f"{name} must lie in the image, 0 to {size} pixels")
        if self.max_range <= self.min_range:
            raise ValueError("max_range must exceed min_range")
        offset = [a - b for a, b in zip(self.look_at, self.position, strict=True)]
        if sum(v * v for v in offset) < 1e-12:
            raise ValueError("look_at must differ from position")
        return self

    def clean(self) -> CameraSpec:
        """This camera without noise, invalid pixels or stray points."""
        return self.model_copy(
            update={"noise_mm": 0.0, "noise_growth_mm": 0.0, "invalid_fraction": 0.0,
                    "stray_fraction": 0.0}
        )  # fmt: skip


class TrackerSpec(Spec):
    """The tracker's options (a GMM-EM tracker of a chain of nodes along the cable)."""

    spacing: float = Field(
        0.025, ge=1.0 / MAX_TRACKER_NODES, le=1.0,
        description="Spacing of the tracked chain's nodes (rod lengths); at least "
        f"1/{MAX_TRACKER_NODES}, a chain of at most {MAX_TRACKER_NODES + 1} nodes.",
    )  # fmt: skip
    iterations: int = Field(8, ge=1, le=200, description="EM iterations per frame.")
    outlier_weight: float = Field(
        0.1, ge=0.0, lt=1.0, description="Prior probability that a point is not the cable's."
    )
    smoothness: float = Field(
        1.0, ge=0.0,
        description="Weight of a seen node's share of the chain's shape: the Laplacian of the "
        "chain's move from its predicted shape.",
    )  # fmt: skip
    hidden_smoothness: float = Field(
        50.0, ge=0.0,
        description="The same weight at a hidden node: a hidden span moves as the seen "
        "cable beside it does.",
    )  # fmt: skip
    bending: float = Field(
        10.0, ge=0.0,
        description="Weight of a seen node's curvature itself (sparse points zigzag; a cable "
        "is smooth).",
    )  # fmt: skip
    hidden_bending: float = Field(
        0.0, ge=0.0, description="The same weight at a hidden node (it keeps its shape)."
    )
    length_sweeps: int = Field(
        40, ge=0, le=1000, description="Sweeps that bring the chain back to its rest spacing."
    )
    prior_weight: float = Field(
        0.02, ge=0.0, description="Pull of a seen node towards its predicted position."
    )
    hidden_weight: float = Field(
        0.01, ge=0.0, description="Pull of a hidden node towards its predicted position."
    )
    visible_support: float = Field(
        0.3, gt=0.0, le=1.0,
        description="A node is seen when the points it explains reach this fraction of the "
        "points per node of the whole cable.",
    )  # fmt: skip
