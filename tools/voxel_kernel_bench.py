#!/usr/bin/env python
"""The query kernels of the voxel (or, ``--backend svo``, the SVO) backend on one stage's bench rays:
the compiled kernel with each instruction set this CPU has, and the Warp kernel; one thread (CPU
seconds of the calling thread) and all cores (wall seconds), with each kernel's agreement with the
Warp kernel.

Usage::

    python tools/voxel_kernel_bench.py stages/city.usda [--backend svo] [--imageWidth 128] [--rounds 3] [--json]

The rays are ``usdml bench``'s (every facing pixel x light pair of the G-buffer, in the shading
order); the voxel settings come from the stage and the flags (``usdml bench``'s). Kernels are run in
turn, ``--rounds`` times, and the median is reported.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace


def main(argv: list[str] | None = None) -> int:
    from usdml.params import add_cmdline_args, overrides_from_args

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("stage")
    p.add_argument("--backend", choices=("voxel", "svo"), default="voxel")
    p.add_argument("--imageWidth", type=int, default=128)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", action="store_true")
    add_cmdline_args(p, "bench")
    args = p.parse_args(argv)

    import numpy as np

    from usdml.bench import query_set
    from usdml.render.frame import conform_camera
    from usdml.render.gbuffer import build_gbuffer
    from usdml.scene import diff
    from usdml.stage import StageDelegate
    from usdml.visibility import ExactBackend, make_backend
    from usdml.visibility.svo import native as svo_native
    from usdml.visibility.voxel import native as voxel_native

    native_lib = voxel_native if args.backend == "voxel" else svo_native
    delegate = StageDelegate(args.stage)
    settings = delegate.usdml_settings.updated(visibility=args.backend, **overrides_from_args(args))
    snap = delegate.snapshot(delegate.start_time)
    w, h = snap.camera.resolution(args.imageWidth)
    with ExactBackend() as exact:
        exact.update(snap)
        gb = build_gbuffer(replace(snap, camera=conform_camera(snap.camera, w, h)), exact, w, h)
    o, t, n, di, _ = query_set(snap, gb)
    o, t, n = (np.ascontiguousarray(x, np.float32) for x in (o, t, n))
    di = np.ascontiguousarray(di, np.int32)
    kernels = [("warp", {"cpu_kernel": "warp"})]
    if native_lib.library() is not None:
        isas = ["scalar"] + (["avx2"] if native_lib.isa_width("avx2") == 8 else [])
        if native_lib.isa_width() > 8:
            isas.append("auto")
        kernels += [(isa, {"cpu_kernel": "native", "native_isa": isa}) for isa in isas]
    quiet = {"report": lambda line: None}
    backends = {}
    for name, kw in kernels:
        b = make_backend(args.backend, settings, "cpu", **kw, **quiet)
        b.update(snap, diff(None, snap))
        b.occluded(o[:1024], t[:1024], normals=n[:1024], distant=di[:1024])
        backends[name] = b
    one, every, answers = {k: [] for k in backends}, {k: [] for k in backends}, {}
    for _ in range(max(1, args.rounds)):
        for name, b in backends.items():
            t0 = time.thread_time()
            if args.backend == "voxel" and b._native is not None:
                out = np.empty(len(o), np.float32)
                b._native.query(b._native_rule(), 0, len(o), o, t, n, di, False, out)
                occ = out >= 0
            else:
                b.workers = 1
                occ = b.occluded(o, t, normals=n, distant=di)
            one[name].append(time.thread_time() - t0)
            from usdml.parallel import cpu_workers
            b.workers = cpu_workers("cpu")
            t0 = time.perf_counter()
            occ_all = b.occluded(o, t, normals=n, distant=di)
            every[name].append(time.perf_counter() - t0)
            answers[name] = occ_all
            assert np.array_equal(occ, occ_all)
    rows = []
    for name, b in backends.items():
        s1, sa = float(np.median(one[name])), float(np.median(every[name]))
        rows.append({"kernel": b.kernel_name, "queries": len(o), "ns_per_query_one_thread": 1e9 * s1 / len(o),
                     "queries_per_second": len(o) / sa, "threads": b.workers,
                     "agreement_with_warp": float((answers[name] == answers["warp"]).mean()),
                     "differing_answers": int((answers[name] != answers["warp"]).sum())})
        b.close()
    if args.json:
        print(json.dumps({"stage": args.stage, "image_width": args.imageWidth, "rows": rows}, indent=1))
    else:
        for r in rows:
            print(f"{r['kernel']:>14}: {r['ns_per_query_one_thread']:6.1f} ns/query on one thread, "
                  f"{r['queries_per_second'] / 1e6:6.1f} M/s on {r['threads']}; "
                  f"{100 * r['agreement_with_warp']:.4f} % as Warp ({r['differing_answers']} differ)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
