"""usdml's one settings object, with the papers' defaults.

Fed, in increasing priority, from these defaults, the stage's ``UsdmlRenderSettingsAPI`` attributes
on its RenderSettings prim, and command-line flags.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

#: schema attribute name -> settings field
SCHEMA_ATTRIBUTES = {
    "usdml:visibility": "visibility",
    "usdml:voxel:resolution": "voxel_resolution",
    "usdml:voxel:directionStep": "direction_step",
    "usdml:voxel:fullyDynamic": "fully_dynamic",
    "usdml:voxel:rebuild": "voxel_rebuild",
    "usdml:voxel:mapping": "voxel_mapping",
    "usdml:gi": "gi",
    "usdml:vpl:bounces": "vpl_bounces",
    "usdml:vpl:count": "vpl_count",
    "usdml:lgh:alpha": "lgh_alpha",
    "usdml:lgh:levels": "lgh_levels",
    "usdml:lgh:interleave": "interleave",
    "usdml:lgh:startLevel": "lgh_start_level",
    "usdml:shadow:samples": "shadow_samples",
    "usdml:shadow:filterIterations": "shadow_filter_iterations",
    "usdml:shadow:targets": "shadow_targets",
    "usdml:pixelSamples": "pixel_samples",
    "usdml:seed": "seed",
}

#: most primary rays per pixel (a 32 x 32 grid)
MAX_PIXEL_SAMPLES = 1024

VISIBILITY_BACKENDS = ("exact", "voxel", "insm", "svo")
GI_METHODS = ("none", "lgh", "vpl-bruteforce")
VOXEL_REBUILDS = ("rotate", "geometry")
VOXEL_MAPPINGS = ("point", "conservative")
SHADOW_TARGETS = ("cluster", "jitter")


@dataclass(frozen=True)
class UsdmlSettings:
    visibility: str = "exact"       #: visibility backend
    voxel_resolution: int = 128     #: voxels per axis of each direction voxelization (paper 000)
    direction_step: float = 2.0     #: degrees between direction bins, k in paper 000 (90 x 90 at 2 deg)
    fully_dynamic: bool = False     #: re-voxelize the whole scene each frame (paper 000, Alg. 5)
    voxel_rebuild: str = "rotate"   #: per-frame arrays by rotation (Alg. 5) or from geometry (Alg. 1)
    voxel_mapping: str = "point"    #: Alg. 5's mapping of rotated voxels: point (paper) or conservative
    gi: str = "none"                #: global illumination: none, lgh, vpl-bruteforce (paper 004)
    vpl_count: int = 100_000        #: VPLs per frame (paper 004 uses 100K)
    vpl_bounces: int = 3            #: diffuse bounces of the VPL light paths (paper 004)
    lgh_alpha: float = 1.0          #: LGH blending radius factor, r_l = alpha h_l (paper 004)
    lgh_levels: int = 0             #: LGH levels; 0 = largest count with |S1| < VPLs / 2 (paper 004)
    lgh_start_level: int = 1        #: finest LGH level lit from: 1 = S1 (paper 004), 0 = the VPLs themselves (S0)
    interleave: int = 1             #: interleaved sampling tile size (1, 2 or 4; paper 004 §4)
    shadow_samples: int = 4         #: stochastic shadow samples per pixel (paper 004)
    shadow_filter_iterations: int = -1  #: à-trous iterations over the shadows; 0 = unfiltered, -1 = by samples
    shadow_targets: str = "cluster" #: LGH shadow rays to a VPL of the grid light (cluster) or its jittered centre (paper)
    dome_samples: int = 256         #: distant lights a dome light is importance-sampled into, per frame
    pixel_samples: int = 4          #: stratified primary rays per pixel (s x s), box filter; 1 = the pixel centre
    seed: int = 0

    def __post_init__(self) -> None:
        from usdml.errors import UsdmlError

        if self.visibility not in VISIBILITY_BACKENDS:
            raise UsdmlError(f"unknown visibility backend {self.visibility!r}; use one of {', '.join(VISIBILITY_BACKENDS)}")
        for name in ("voxel_resolution", "vpl_count", "shadow_samples", "dome_samples"):
            if getattr(self, name) < 1:
                raise UsdmlError(f"setting {name} must be >= 1, got {getattr(self, name)}")
        if not 0 < self.direction_step <= 90:
            raise UsdmlError(f"direction step must be in (0, 90] degrees, got {self.direction_step}")
        if not (0 < self.lgh_alpha < float("inf")) or self.lgh_levels < 0:
            raise UsdmlError(f"LGH alpha must be finite and > 0 and levels >= 0, got alpha {self.lgh_alpha} and "
                             f"{self.lgh_levels} levels")
        if self.seed < 0:
            raise UsdmlError(f"seed must be >= 0, got {self.seed}")
        if self.voxel_rebuild not in VOXEL_REBUILDS:
            raise UsdmlError(f"unknown voxel rebuild {self.voxel_rebuild!r}; use one of {', '.join(VOXEL_REBUILDS)}")
        if self.voxel_mapping not in VOXEL_MAPPINGS:
            raise UsdmlError(f"unknown voxel mapping {self.voxel_mapping!r}; use one of {', '.join(VOXEL_MAPPINGS)}")
        if self.gi not in GI_METHODS:
            raise UsdmlError(f"unknown global illumination {self.gi!r}; use one of {', '.join(GI_METHODS)}")
        if self.lgh_start_level not in (0, 1):
            raise UsdmlError(f"LGH start level must be 0 (S0, the VPLs) or 1 (S1, the paper's), got {self.lgh_start_level}")
        if not -1 <= self.shadow_filter_iterations <= 10:
            raise UsdmlError(f"shadow filter iterations must be in 0..10, or -1 for automatic, "
                             f"got {self.shadow_filter_iterations}")
        if self.shadow_targets not in SHADOW_TARGETS:
            raise UsdmlError(f"unknown shadow targets {self.shadow_targets!r}; use one of {', '.join(SHADOW_TARGETS)}")
        if self.interleave not in (1, 2, 4):
            raise UsdmlError(f"interleave must be 1, 2 or 4, got {self.interleave}")
        s = round(self.pixel_samples ** 0.5)
        if s * s != self.pixel_samples or not 1 <= self.pixel_samples <= MAX_PIXEL_SAMPLES:
            raise UsdmlError(f"pixel samples must be a square number from 1 to {MAX_PIXEL_SAMPLES} (1, 4, 9, 16, ...: "
                             f"an s x s stratified grid), got {self.pixel_samples}")
        if self.vpl_bounces < 1:
            raise UsdmlError(f"VPL bounces must be >= 1, got {self.vpl_bounces}")

    def updated(self, **values) -> "UsdmlSettings":
        """A copy with the given non-None values replaced."""
        return replace(self, **{k: v for k, v in values.items() if v is not None})

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}
