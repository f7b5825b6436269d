"""The voxel method (paper 000)'s rows of the parameter table (:mod:`usdml.params`): its settings, declared with the method
and joined to the table through the backend registry (``usdml.visibility.registry``). A leaf module: it imports only :mod:`usdml.param`, so the table is built without
importing the backend."""

from __future__ import annotations

from usdml.param import VIS, Param, Range

#: when the voxel arrays are read (``Param.applies``)
VOXEL = (("visibility", ("voxel",)),)

#: the voxel backend's settings, in the order of the flags' help
PARAMS = (
    Param("voxel_resolution", int, 128, "voxels per axis of each direction's voxelization", **VIS,
          range=Range(4, 2048), metavar="N", applies=VOXEL, source="paper 000",
          doc="""Voxels per axis of each direction voxelization (paper 000 uses 128).

    Each voxelization holds resolution^3 bits: at 128 and a 2 degree
    direction step, the 90 x 90 array takes just under 2 GB."""),
    Param("direction_step", float, 2.0, "degrees between direction bins (k in paper 000: 90 x 90 directions at 2)",
          **VIS, attribute="usdml:voxel:directionStep", range=Range(0.1, 90), metavar="DEG", source="paper 000",
          doc="""Angular increment k, in degrees, of the (theta, phi) grid of voxelization directions (paper 000 uses 2).

    theta and phi each run from 0 to 180 degrees in steps of k, so k = 2
    gives 90 x 90 voxelizations; a ray uses the voxelization whose row
    direction is closest to its own."""),
    Param("fully_dynamic", bool, False, "voxelize the whole scene every frame (paper 000 Alg. 5) instead of a "
          "static array plus prototype arrays", **VIS, attribute="usdml:voxel:fullyDynamic",
          source="paper 000 (Alg. 4 unless the scene asks for Alg. 5)",
          doc="""Re-voxelize the whole scene every frame, for scenes where much moves or deforms (paper 000, Algorithm 5).

    Each frame one voxelization is computed and rotated with two degrees
    of freedom to approximate the whole array, as paper 000 does for its
    amusement park. When false, the static scene is voxelized once and
    rigid instances reuse their prototype's voxelizations by transforming
    rays into prototype space (paper 000, Algorithm 4)."""),
    Param("voxel_rebuild", str, "rotate", "per-frame voxel arrays (deforming meshes, fully dynamic scenes): "
          "rotate one voxelization (paper 000 Alg. 5) or voxelize every direction (Alg. 1)", **VIS,
          choices=("rotate", "geometry"), applies=VOXEL, source="paper 000, Alg. 5",
          doc="""How voxel arrays rebuilt every frame (deforming meshes, or the whole scene when fullyDynamic) are made: rotate or geometry.

    "rotate" voxelizes the frame's geometry once and fills every other
    direction by rotating it (paper 000, Algorithm 5); "geometry"
    voxelizes every direction from the geometry (Algorithm 1), slower
    and more accurate."""),
    Param("voxel_mapping", str, "point", "Alg. 5: a rotated voxel sets the voxel of its centre (point, the paper) "
          "or every voxel it overlaps (conservative)", **VIS, choices=("point", "conservative"), applies=VOXEL,
          source="paper 000, Alg. 5",
          doc="""How a rotated voxel marks the target voxelization in Algorithm 5: point or conservative.

    "point" (the paper) sets the voxel holding the rotated voxel's
    centre, leaving some holes in tilted surfaces; "conservative" sets
    every voxel the rotated voxel overlaps: no holes, thicker surfaces,
    slower."""),
    # leaving the surface (usdml.visibility.voxel.backend's module doc): usdml's measured rule, not the paper's
    Param("voxel_normal_offset", float, 1.0, "voxels (of the static array) a shadow ray starts off its surface, "
          "along the normal turned toward the light", **VIS, range=Range(0), metavar="VOXELS", applies=VOXEL,
          source="measured (usdml)",
          doc="""Voxels (of the static array, in world units) a shadow ray starts off its surface, along the normal turned toward the light.

    Occluders closer than about normalOffset + slab voxels to the shading
    point do not shadow."""),
    Param("voxel_skip", float, 1.0, "voxels a shadow ray ignores at its start to leave its own surface (more at "
          "grazing angles)", **VIS, range=Range(0), metavar="VOXELS", applies=VOXEL, source="measured (usdml)"),
    Param("voxel_slab", float, 1.0, "voxels above the tangent plane a grazing shadow ray skips to (slab / "
          "sin(angle) along the ray, at most the max skip)", **VIS, range=Range(0), metavar="VOXELS", applies=VOXEL,
          source="measured (usdml)"),
    Param("voxel_max_skip", float, 0.0, "most voxels a grazing shadow ray skips to leave its surface; 0 = "
          "automatic: 2, or 4 with the conservative mapping", **VIS, range=Range(0), metavar="VOXELS",
          applies=VOXEL, source="measured (usdml): 2 point, 4 conservative"),
    Param("voxel_end_skip", float, 1.0, "voxels a shadow ray ignores at the light's end, so a light mounted on a "
          "wall is not hidden by it", **VIS, range=Range(0), metavar="VOXELS", applies=VOXEL,
          source="measured (usdml)"),
    Param("voxel_segment", int, 32, "voxels a shadow ray looks up in one row before it picks its row anew (a "
          "divisor of 32)", **VIS, choices=(1, 2, 4, 8, 16, 32), applies=VOXEL, source="one 32-bit word of a row"),
    Param("voxel_cpu_kernel", str, "auto", "how voxel queries run on a CPU: auto (the compiled kernel, AVX2 where "
          "the CPU has it, else Warp), native (the compiled kernel; an error without it) or warp", **VIS,
          choices=("auto", "native", "warp"), applies=VOXEL, source="measured (usdml): docs/voxel.md",
          doc="""How voxel shadow queries run on a CPU: auto, native or warp.

    "native" is the compiled kernel built at install (8 queries at a
    time with AVX2 when the CPU has it, else one at a time); "warp" the
    Warp kernels (also what a GPU runs); "auto" the compiled kernel when
    it was built, else Warp."""),
    Param("voxel_core", float, 0.0, "voxelization rule of the cached arrays: 0 rasterizes rows' centre lines; a "
          "fraction > 0 marks surface samples in that central part of a row", **VIS, range=Range(0, 1),
          metavar="FRACTION", applies=VOXEL, source="measured (usdml)"),
    # Alg. 1's per-frame arrays, measured at 128^3 / 2 deg (e_v / e_s, rebuild): low-poly creature (3,968 triangles)
    # 1: 1.85 / 1.19 %, 6.4 s; 0: 1.77 / 1.08 %, 1.3 s; park 1: 32.0 / 29.0 %, 3.0 s; 0: 19.0 / 9.6 %, 1.6 s
    Param("voxel_frame_core", float, 0.0, "the same rule for per-frame arrays rebuilt from geometry (voxel "
          "rebuild geometry)", **VIS, range=Range(0, 1), metavar="FRACTION", applies=VOXEL,
          source="measured (usdml)",
          doc="""Voxelization rule of per-frame arrays rebuilt from geometry (rebuild = geometry), as core."""),
    Param("voxel_memory_limit", float, 0.0, "GiB the voxel arrays may take; 0 = automatic: 80 % of the available "
          "memory", **VIS, range=Range(0), metavar="GIB", applies=VOXEL, source="the machine"),
)
