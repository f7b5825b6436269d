#!/usr/bin/env python
"""The measured tables of ``docs/benchmarks.md``, written from the tools' JSON kept in ``docs/data/``.

Usage::

    python tools/bench_tables.py             # rewrite every table between its markers
    python tools/bench_tables.py --check     # exit 1 (with a diff) if a table is not what its data says
    python tools/bench_tables.py --list      # each table: where its data came from, and its commands
    python tools/bench_tables.py --untied    # each figure in prose that no marker ties to data
    python tools/bench_tables.py --run NAME  # re-run NAME's commands, keep their JSON, rewrite the tables
    python tools/bench_tables.py --run NAME --commands 0,2   # only those commands (numbered as --list shows)

Each table ``NAME`` has one data file ``docs/data/NAME.json``: the commands that measured it, each with
its JSON output as the tool printed it (``--json``) and a ``source`` saying when and where it was
measured (or that the figures were carried over from an earlier README and await re-measuring). In a
page under ``docs/``, the table sits between ``<!-- table: NAME -->`` and ``<!-- /table -->``; what is
between the markers is generated (the table, then the commands), so edit the data, not the page.

A figure in prose is tied to its data the same way: ``<!-- fig: NAME -->8.15 %<!-- /fig -->``, where
``NAME`` is a key of ``FIGURES`` below (a data file, a path into it, a format); the text between the
markers is generated, in ``README.md`` and every page under ``docs/``. ``--check`` also counts the
figures a page states outside tables, code and markers (a number with ``×``, ``%``, ``s``, ``ms``,
``M/s``, ...): a page may state none (``UNTIED`` names the one section still being tied), so a new
measured figure comes with its data or does not come; a result measured once, that no tool keeps, goes
to ``docs/CHANGELOG.md``, which is history, dated by commit, and is not checked. A figure that looks
measured but is not is marked for what it is: ``<!-- paper -->10×<!-- /paper -->`` a figure a paper
reports, ``<!-- set -->5 %<!-- /set -->`` a value chosen (a default, a tolerance, a test's bound, a
colour scale), ``<!-- calc -->0.8 %<!-- /calc -->`` one worked out from the model's equations; such a
marker holds exactly one figure.

``--run`` needs usdml installed (the commands are ``python tools/...`` and ``usdml ...``; both are run
with this interpreter); the rest is the standard library only.
"""

from __future__ import annotations

import argparse
import datetime
import difflib
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
DATA = DOCS / "data"
MARKER = re.compile(r"(<!-- table: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /table -->)", re.S)
FIG = re.compile(r"(?<!`)(<!-- fig: (?P<name>[\w.-]+) -->)(?P<body>.*?)(<!-- /fig -->)", re.S)
CHANGELOG = DOCS / "CHANGELOG.md"


# ------------------------------------------------------------------------------------------- formatting


def _span(x, fmt) -> str:
    """``fmt`` of a figure, or ``lo–hi`` of a ``[lo, hi]`` range measured over several runs."""
    if isinstance(x, (list, tuple)):
        return "–".join(fmt(v) for v in x)
    return fmt(x)


def _pct(x) -> str:
    """A fraction as a percentage: two decimals under 10 %, one above."""
    return _span(x, lambda v: f"{100 * v:.2f}" if abs(100 * v) < 10 else f"{100 * v:.1f}") + " %"


def _pct3(x) -> str:
    """A fraction as a percentage to three significant digits (``6.90 %``, ``14.0 %``, ``0.723 %``)."""
    return _span(x, lambda v: f"{100 * v:#.3g}".rstrip(".")) + " %"


def _estimate(value: float, interval) -> str:
    """An estimate and its 95 % interval: ``6.90 % [5.2, 8.6]``."""
    lo, hi = interval
    return f"{_pct3(value)} [{100 * lo:.3g}, {100 * hi:.3g}]"


def _stage(path: str) -> str:
    return Path(path).name.removesuffix(".usda")


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(r) + " |" for r in rows]


def _runs(data: dict) -> list[dict]:
    """Every command of a data file, in order (``rows`` of ``voxel-alg5`` hold two each)."""
    if "runs" in data:
        return data["runs"]
    return [run for row in data["rows"] for run in (row.get("compare"), row.get("bench")) if run]


# -------------------------------------------------------------------------------------------- renderers


def voxel_rows(data: dict) -> list[str]:
    """``tools/voxel_table.py --json``: one row per stage, resolution and direction step."""
    rows = []
    for run in data["runs"]:
        for r in run["output"]:
            frame = (f"{r['frame_seconds']:.1f} ({r['exact_frame_seconds']:.1f})"
                     if r.get("frame_seconds") is not None else "–")
            rows.append([_stage(r["stage"]), f"{r['voxel_resolution']}³ / {r['direction_step']:g}°",
                         _pct(r["eps_v"]), _pct(r["eps_s"]),
                         f"{100 * r['wrongly_hidden']:.2f} / {100 * r['wrongly_visible']:.2f}",
                         f"{r['build_seconds']:.1f}", f"{r['bytes'] / 2 ** 20:.0f} MiB",
                         _span(r["queries_per_second"], lambda v: f"{v / 1e6:.1f}") + " M",
                         _span(r["speedup_vs_exact"], lambda v: f"{v:.2f}") + "×", frame])
    return _table(["stage", "grid", "ε_v", "ε_s", "hidden / visible (% pairs)", "build s", "bytes", "queries/s",
                   "vs exact", "frame s (exact)"], rows)


def voxel_alg5(data: dict) -> list[str]:
    """``usdml compare --json`` (ε) and ``usdml bench --json`` (per-frame rebuild) per row."""
    rows = []
    for row in data["rows"]:
        c = row["compare"]["output"]
        b = next((r for r in row["bench"]["output"] if r["backend"] == "voxel"), {}) if row.get("bench") else {}
        how = row["rebuild"]
        if how == "alg5":
            rebuild = (f"{b['rebuild_seconds']:.2f} s (Alg. 1: {b['full_rebuild_seconds']:.2f} s, "
                       f"{b['rebuild_speedup']:.2g}×)")
        elif how == "alg5-ratio":
            rebuild = f"{b['rebuild_seconds']:.2f} s ({b['rebuild_speedup']:.2g}×)"
        elif how == "alg1":
            rebuild = f"{b['full_rebuild_seconds']:.2f} s"
        else:
            rebuild = "none"
        rows.append([row["label"], rebuild, _pct3(c["eps_v"]), _pct3(c["eps_s"]), row.get("paper", "")])
    return _table(["stage, 128³ / 2°", "per-frame rebuild", "ε_v", "ε_s", "paper 000 Table I"], rows)


def light_scaling(data: dict) -> list[str]:
    """``tools/light_scaling.py --json``: seconds per frame, one column per light count."""
    counts = list(dict.fromkeys(r["lights"] for run in data["runs"] for r in run["output"]))
    rows = []
    for run in data["runs"]:
        by_n = {r["lights"]: r for r in run["output"]}
        cell = lambda n, f: f(by_n[n]) if n in by_n else "–"  # noqa: E731
        rows.append([f"{run['label']} voxel (of which rebuild)"] + [
            cell(n, lambda r: f"{r['voxel']['seconds']:.2f} ({r['voxel']['rebuild_seconds']:.2f})") for n in counts])
        rows.append([f"{run['label']} exact"] + [cell(n, lambda r: f"{r['exact']['seconds']:.2f}") for n in counts])
    return _table(["lights"] + [f"{n:,}" for n in counts], rows)


def frame_speed(data: dict) -> list[str]:
    """``tools/light_scaling.py --json`` at one light count: a frame's seconds and their split per backend."""
    rows = []
    for run in data["runs"]:
        for r in run["output"]:
            w, h = r["exact"]["resolution"]
            for name in [n for n in ("voxel", "svo", "insm") if n in r] + ["exact"]:
                b = r[name]
                rows.append([f"{_stage(r['stage'])} {w}×{h}, {r['lights']:,} lights", f"`{name}`",
                             f"{b['seconds']:.2f}", f"{b['update_seconds']:.2f}", f"{b['gbuffer_seconds']:.2f}",
                             f"{b['shading_seconds']:.2f}",
                             f"{r[name + '_speedup_vs_exact']:.1f}×" if name != "exact" else "1×"])
    return _table(["frame", "backend", "seconds", "update", "G-buffer", "shading (queries and light sums)",
                   "vs exact"], rows)


def gi_lgh(data: dict) -> list[str]:
    """``tools/gi_table.py --json``: one row per run, its S0 settings side by side (S1 in brackets)."""
    rows = []
    for run in data["runs"]:
        out = run["output"]
        s0 = [r for r in out["rows"] if r["start_level"] == 0]
        s1 = {r["shadow_samples"]: r for r in out["rows"] if r["start_level"] == 1}
        ks = " / ".join(str(r["shadow_samples"]) for r in s0)
        err = " / ".join(f"{100 * r['rel_rmse']:.1f}" for r in s0) + " %"
        if len(s0) == 1 and s0[0]["shadow_samples"] in s1:
            err += f" (S1: {100 * s1[s0[0]['shadow_samples']]['rel_rmse']:.1f} %)"
        speed = " / ".join(f"{r['speedup']:.0f}×" for r in s0)
        w, h = out["resolution"]
        stage = _stage(out["stage"])
        alphas = {r["alpha"] for r in s0}
        if alphas != {2.0}:
            stage += ", α " + " / ".join(f"{x:g}" for x in sorted(alphas))
        if out.get("visibility", "exact") != "exact":
            stage += f", {out['visibility']} rays"
        rows.append([stage, f"{out['vpls']:,}", f"{w}×{h}", ks, err, speed])
    return _table(["stage", "VPLs", "image", "k", "rel. RMSE of `indirect`", "speed-up over brute force"], rows)


def lgh_build(data: dict) -> list[str]:
    """``tools/lgh_build_times.py --json``: median build in ms, one column per stage."""
    counts = list(dict.fromkeys(r["vpls"] for run in data["runs"] for r in run["output"]["rows"]))
    cols = [(_stage(run["output"]["stage"]), {r["vpls"]: r for r in run["output"]["rows"]}) for run in data["runs"]]
    rows = [[f"{n:,}"] + [f"{1000 * c[n]['seconds']:.4g}" if n in c else "–" for _, c in cols] for n in counts]
    return _table(["VPLs"] + [name for name, _ in cols], rows)


def gi_reference(data: dict) -> list[str]:
    """``tools/gi_reference.py --json``: energy and block error against Mitsuba, furnace against ρ + … + ρ^B."""
    rows = []
    for run in data["runs"]:
        labels = {**data.get("labels", {}), **run.get("labels", {})}       # a run's own labels first
        for method, r in run["output"]["methods"].items():
            rows.append([labels.get(method, f"`{method}`"), f"{r['indirect_ratio']:.3f}",
                         f"{100 * r['block_error']:.1f} %", f"{r['furnace_ratio']:.4g}"])
    return _table(["method", "box energy", "box block error", "furnace"], rows)


def anti_aliasing(data: dict) -> list[str]:
    """``tools/reference_compare.py --json``: ``direct`` against the pixel-integrated reference per N."""
    rows = []
    for run in data["runs"]:
        for n, r in run["output"]["pixel_samples"].items():
            rows.append([str(n), _pct3(r["direct_rel_rmse"]), f"{r['seconds_per_frame']:.2f}"])
    return _table(["pixel samples N", "rel. RMSE of `direct`", "seconds per frame"], rows)


def bench(data: dict) -> list[str]:
    """``usdml bench --json``: the voxel backend's queries per second beside Embree's (through the exact
    backend, and bare embreex where the run measured it), same queries, and the CPU kernel answering."""
    rows = []
    for run in data["runs"]:
        for r in run["output"]:
            if r["backend"] == "exact":
                continue
            bare = r.get("speedup_vs_bare_embree")
            rows.append([_stage(r["stage"]), f"`{r['backend']}`" + (f" ({r['cpu_kernel']})" if r.get("cpu_kernel") else ""),
                         f"{r['voxel_resolution']}³ / {r['direction_step']:g}°" if "voxel_resolution" in r else
                         f"{r['svo_resolution']}³ octree" if "svo_resolution" in r else "–",
                         _span(r["queries_per_second"], lambda v: f"{v / 1e6:.1f}") + " M",
                         _span(r["speedup_vs_exact"], lambda v: f"{v:.2f}") + "×",
                         "–" if bare is None else f"{bare:.2f}×"])
    return _table(["stage", "backend (kernel)", "grid", "queries/s", "vs exact", "vs bare embreex"], rows)


def voxel_kernels(data: dict) -> list[str]:
    """``tools/voxel_kernel_bench.py --json``: each query kernel (voxel, or SVO) on one stage's bench rays."""
    rows = []
    for run in data["runs"]:
        out = run["output"]
        for r in out["rows"]:
            rows.append([_stage(out["stage"]), f"`{r['kernel']}`", f"{r['ns_per_query_one_thread']:.1f}",
                         f"{r['queries_per_second'] / 1e6:.1f} M ({r['threads']})",
                         f"{100 * r['agreement_with_warp']:.4f} % ({r['differing_answers']:,} of {r['queries']:,} differ)"])
    return _table(["stage", "kernel", "ns / query, one thread", "queries/s (threads)", "answers as the Warp kernel"], rows)


def svo_rows(data: dict) -> list[str]:
    """``usdml compare --visibility svo --json``: one row per stage and resolution."""
    rows = []
    for run in data["runs"]:
        r = run["output"]
        build = r.get("tree_build_seconds") or 0.0
        rows.append([_stage(r["stage"]), f"{r['svo_resolution']}³", _pct(r["eps_v"]), _pct(r["eps_s"]),
                     f"{100 * r['wrongly_hidden']:.2f} ({100 * r['wrongly_hidden_near']:.2f} near) / "
                     f"{100 * r['wrongly_visible']:.2f}",
                     f"{r['bytes'] / 2 ** 20:.2f} MiB", f"{r['occupied_voxels']:,}",
                     f"{build:.2f}" if build else "cached", f"{r['speedup']:.2f}×"])
    return _table(["stage", "grid", "ε_v", "ε_s", "hidden (near) / visible, % pairs", "tree bytes", "voxels",
                   "static build s", "queries vs exact"], rows)


def svo_rebuild(data: dict) -> list[str]:
    """``usdml bench --visibility exact --visibility svo --json``: the per-frame tree's rebuild."""
    rows = []
    for run in data["runs"]:
        for r in run["output"]:
            if r["backend"] != "svo":
                continue
            rows.append([_stage(r["stage"]), f"{r['svo_resolution']}³", f"{r['rebuild_triangles']:,}",
                         f"{r['occupied_voxels']:,}", f"{r['voxelize_seconds']:.3f}", f"{r['rebuild_seconds']:.3f}",
                         f"{r['speedup_vs_exact']:.2f}×"])
    return _table(["stage", "grid", "triangles per frame", "voxels (per-frame tree)", "voxelize s", "rebuild s",
                   "queries vs exact"], rows)


def insm_rows(data: dict) -> list[str]:
    """``tools/insm_table.py --json``: paper 001's Tables 2-4, one row per setting of each sweep."""
    rows = []
    names = {"insm_resolution": "w", "insm_light_resolution": "S", "insm_count": "K"}
    for run in data["runs"]:
        for r in (run["output"] or {}).get("rows", []):          # not yet measured: no rows
            cells = [f"**{r[f]}**" if f == r["sweep"] else str(r[f]) for f in names]
            rows.append([_stage(r["stage"]), names[r["sweep"]], *cells, _pct(r["eps_v"]), _pct(r["eps_s"]),
                         f"{_pct(r['wrongly_visible'])} / {_pct(r['wrongly_hidden'])}", f"{r['triangles']:,}",
                         f"{r['frame_seconds']:.1f}", f"{r['exact_seconds']:.2f}"])
    return _table(["stage", "swept", "w (depth images)", "S (light maps)", "K", "ε_v", "ε_s",
                   "wrongly visible / hidden (of pairs)", "reconstructed triangles", "insm s per frame",
                   "exact queries s"], rows)


def insm_dynamic(data: dict) -> list[str]:
    """``tools/insm_table.py --dynamic --json``: a frame whose geometry moved against the same frame again."""
    rows = []
    for run in data["runs"]:
        for r in (run["output"] or {}).get("dynamic", []):
            w, h = r["resolution"]
            moving = min(r["moving"], key=lambda x: x["seconds"])
            rows.append([f"{_stage(r['stage'])} {w}×{h}, {moving['lights']:,} lights", f"{r['triangles']:,}",
                         f"{r['moving_seconds']:.2f}", f"{r['still_seconds']:.2f}", f"{r['moving_over_still']:.2f}",
                         f"{moving['depth_seconds'] + moving['triangulate_seconds']:.2f}"])
    return _table(["frame", "reconstructed triangles", "geometry moved: s", "nothing moved: s", "ratio",
                   "depth images + triangulation s"], rows)


def dome_error(data: dict) -> list[str]:
    """``tools/dome_error.py --json``: ``direct`` with K dome samples against K = ``reference_samples``."""
    rows = []
    for run in data["runs"]:
        out = run["output"]
        for r in out["rows"]:
            rows.append([f"{r['samples']:,}", _pct3(r["rel_rmse"]), f"{r['seconds']:.2f}"])
        rows.append([f"{out['reference_samples']:,} (reference)", "–", f"{out['reference_seconds']:.2f}"])
    return _table(["dome samples K", "rel. RMSE of `direct`", "seconds per frame"], rows)


def gi_svo(data: dict) -> list[str]:
    """``tools/svo_gi_table.py --json``: accuracy and speed per VPL count and ray backend, then paper 003
    Table 1's stage timings beside usdml's."""
    rows, stages = [], []
    for run in data["runs"]:
        out = run["output"]
        w, h = out["resolution"]
        for r in out["rows"]:
            for name, v in r["rays"].items():
                rows.append([f"{r['vpls']:,}", f"{w}×{h}", f"`{name}`", _pct(v["rel_rmse"]),
                             f"{v['seconds']:.2f} ({r['bruteforce_seconds']:.2f})", f"{v['speedup']:.1f}×",
                             f"{v['shadow_rays'] / r['bruteforce_rays']:.3f}",
                             f"{v['visibility_seconds']:.2f}"])
        stages.append(out)
    lines = _table(["VPLs", "image", "svo's rays", "rel. RMSE of `indirect`", "indirect pass s (brute force)",
                    "speed-up", "rays / brute force's", "ray thread-s"], rows)
    for out in stages:
        paper = out["paper"]
        by = {r["vpls"]: r["stages"] for r in out["rows"]}
        counts = sorted(by)
        sw, sh = out["stage_resolution"]
        ms = lambda key: " / ".join(_ms(by[n][key]) for n in counts)  # noqa: E731
        pp = lambda key: " / ".join(f"{v:g}" for v in paper[key])  # noqa: E731
        backend = by[counts[0]]["backend"]
        lines += ["", _table_title(f"stage, ms at {' / '.join(f'{n:,}' for n in counts)} VPLs",
                                   f"paper 003 ({paper['resolution'][0]}×{paper['resolution'][1]}, "
                                   f"{paper['svo']} SVO, Titan X)", f"usdml ({sw}×{sh}, `{backend}` rays, 2 CPUs)")]
        lines += [
            f"| voxelization and SVO build | {pp('voxelization_svo_ms')} | "
            + ("– (exact rays: the BVH the primary rays use)" if backend == "exact" else
               f"{ms('backend_build')} (from the cache: {ms('backend_update')})") + " |",
            f"| RSM + VPL generation (usdml: light paths) | {pp('rsm_ms')} + {pp('vpl_generation_ms')} | "
            f"{ms('vpl_generation')} |",
            f"| direct illumination | {pp('direct_ms')} | {ms('direct')} |",
            f"| indirect illumination | {pp('indirect_ms')} | "
            + " / ".join(_ms(by[n]["gather"] + by[n]["filter"]) for n in counts) + " |",
            f"| of which: gather (its rays, thread-ms) + filter | – | {ms('gather')} ({ms('visibility')}) + "
            f"{ms('filter')} |",
        ]
    return lines


def _times(x: float) -> str:
    """A speed-up: one decimal under 10×."""
    return f"{x:.1f}×" if x < 10 else f"{x:.0f}×"


def direct_lgh(data: dict) -> list[str]:
    """``tools/direct_lgh_scaling.py --json``: --direct lgh against --direct all per light count."""
    rows = []
    for run in data["runs"]:
        for r in run["output"] or []:
            w, h = r["resolution"]
            growth = f"{r['growth_per_10x']:.2f}×" if r.get("growth_per_10x") else "–"
            rows.append([f"{r['lights']:,}", f"{w}×{h}", f"{r['lgh_seconds']:.2f}", f"{r['all_seconds']:.1f}",
                         r["reference"], _times(r["speedup"]), _pct(r["rel_rmse"]), growth, str(r["lgh_levels"])])
    return _table(["lamps", "pixels", "lgh s per frame", "all s per frame", "reference", "speed-up",
                   "rel. RMSE of direct", "lgh time per 10× lamps", "LGH levels"], rows)


def direct_compare(data: dict) -> list[str]:
    """``usdml compare --direct lgh --against all --json``, one row per run."""
    rows = []
    for run in data["runs"]:
        r = run["output"]
        if not r:
            continue
        w, h = r["resolution"]
        s, d = r["seconds"], r["direct_seconds"]
        ref = "every pixel" if not r["reference_extrapolated"] else f"{r['compared_pixels']:,} pixels, extrapolated"
        rows.append([_stage(r["stage"]), f"{r['lights']:,}", f"{w}×{h}", r["visibility"],
                     str(r["direct_shadow_samples"]), _pct(r["rel_rmse"]), f"{d['lgh']:.2f} / {d['all']:.1f}",
                     _times(r["direct_speedup"]), f"{s['lgh']:.2f} / {s['all']:.1f}", _times(r["speedup"]), ref])
    return _table(["stage", "lights", "pixels", "visibility", "shadow samples", "rel. RMSE of direct",
                   "direct light s (lgh / all)", "speed-up", "frame s (lgh / all)", "frame speed-up", "reference"],
                  rows)


def direct_frame(data: dict) -> list[str]:
    """``tools/direct_lgh_scaling.py --frame-size SIZE --json``: a user's render of one frame with --direct lgh."""
    rows = [[f"{r['lights']:,}", f"{r['resolution'][0]}×{r['resolution'][1]}", str(r["pixel_samples"]),
             r["visibility"], f"{r['seconds']:.1f}"] for run in data["runs"] for r in run["output"] or []]
    return _table(["lamps", "pixels", "pixel samples", "visibility", "usdml render s (all of it)"], rows)


def _ms(seconds: float) -> str:
    """Seconds as milliseconds: whole ones from 10 ms, two significant digits below."""
    v = 1000.0 * seconds
    return f"{v:.0f}" if v >= 10 else f"{v:.2g}"


def _table_title(*header: str) -> str:
    """The header and rule lines of a table, as one string (a table whose rows are written by hand)."""
    return "\n".join(_table(list(header), []))


def budget_rows(data: dict) -> list[str]:
    """``tools/budget_table.py --json``: one row per stage, backend and ``--error-budget``."""
    rows = []
    for run in data["runs"]:
        for r in run["output"]:
            budget = "none" if r["budget"] >= 1 else f"{r['budget']:g}"
            frame = (f"{r['frame_seconds']:.1f} ({r['exact_frame_seconds']:.1f})"
                     if r.get("frame_seconds") is not None else "–")
            rows.append([_stage(r["stage"]), r["visibility"], budget, str(r["refine_level"]), _pct3(r["eps_v"]),
                         _estimate(r["estimated_eps_v"], r["estimated_eps_v_interval"]),
                         "yes" if r["interval_holds"] else "**no**", _pct3(r["eps_s"]),
                         f"{100 * r['refined_fraction']:.1f} / {100 * r['near_fraction']:.1f}",
                         f"{r['speedup']:.2f}×",
                         f"{r['bench_speedup']:.2f}×" if r.get("bench_speedup") is not None else "–", frame,
                         f"{r['shadow_mean_abs']:.4f}" if r.get("shadow_mean_abs") is not None else "–",
                         f"{r['estimate_seconds']:.2f}"
                         + (f" ({100 * r['frame_estimate_share']:.1f} %)" if r.get("frame_estimate_share") is not None
                            else "")])
    return _table(["stage", "backend", "budget", "level", "ε_v", "estimate [95 %]", "holds", "ε_s",
                   "re-asked / blind zone (% queries)", "× exact (compare)", "× exact (bench)", "frame s (exact)",
                   "shadow AOV vs exact (mean abs.)", "estimate s (share of the frame)"], rows)


#: issue 37's targets: (relative RMSE at most, speed-up at least) by mode
LGH_SUITE_TARGETS = {"gi": (0.10, 50.0), "direct": (0.05, 30.0)}
#: --direct lgh on a million lights: the speed-up and the seconds of the frame
LGH_MILLION_TARGET = (100.0, 60.0)


def lgh_suite_rows(data: dict) -> list[str]:
    """``tools/lgh_suite.py --json``: one row per suite stage and mode (``--gi lgh`` at a VPL count, ``--direct
    lgh``), the error against brute force, the speed-up, the frame's own estimate and issue 37's target."""
    rows = []
    for run in data["runs"]:
        for r in sorted(run["output"], key=lambda r: (r["mode"] != "gi", r["kind"], r["lights"], r.get("vpls", 0),
                                                      r["seed"])):
            err, speed = LGH_SUITE_TARGETS[r["mode"]]
            most = None                 # a million lights: 100x and a minute a frame (issue 37)
            if r["mode"] == "direct" and r["lights"] >= 1_000_000:
                speed, most = LGH_MILLION_TARGET
            met = r["rel_rmse"] <= err and r["speedup"] >= speed and (most is None or r["seconds"]["lgh"] <= most)
            what = f"{r['vpls']:,} VPLs" if r["mode"] == "gi" else f"{r['lights']:,} lights"
            est = "–" if r["estimated_rel_rmse"] is None else \
                _estimate(r["estimated_rel_rmse"], r["estimated_interval"])
            holds = "–" if r["estimate_holds"] is None else ("yes" if r["estimate_holds"] else "**no**")
            rows.append([run.get("label", "–"), _stage(r["stage"]), r["split"], f"{r['scale']:g}", f"--{r['mode']} lgh",
                         what,
                         "×".join(map(str, r["resolution"])), _pct3(r["rel_rmse"]), f"{r['speedup']:.1f}×", est, holds,
                         f"≤ {100 * err:g} %, ≥ {speed:g}×" + ("" if most is None else f", ≤ {most:g} s ({r['seconds']['lgh']:.0f})")
                         + ": " + ("yes" if met else "**no**")])
    return _table(["defaults", "stage", "split", "scale", "method", "lights", "pixels", "rel. RMSE", "speed-up",
                   "estimate [95 %]", "holds", "target met"], rows)


def lgh_split_rows(data: dict) -> list[str]:
    """``tools/lgh_suite.py --lgh-split ... --json``: per suite stage and VPL count, ``--gi lgh`` with one
    hierarchy (none), one per normal class (normal) and the frame's choice (auto, the default) side by side,
    each as its own ``usdml compare`` (the error against brute force, the speed-up), and whether the
    default meets issue 37's target."""
    cells: dict = {}
    for run in data["runs"]:
        for r in run["output"]:
            asked = r.get("asked") if r.get("asked") not in (None, "default") else run.get("asked")
            asked = asked or r["settings"]["lgh_split"]
            cells.setdefault((r["kind"], r["lights"], r["seed"], r["vpls"], tuple(r["resolution"]), r["stage"]),
                             {})[asked] = r
    err, speed = LGH_SUITE_TARGETS["gi"]
    rows = []
    for (_, _, _, vpls, _, stage), by in sorted(cells.items(), key=lambda kv: (kv[0][3], kv[0][4], kv[0][:3])):
        any_row = next(iter(by.values()))
        row = [_stage(stage), any_row["split"], f"{vpls:,}", "×".join(map(str, any_row["resolution"]))]
        for asked in ("none", "normal", "auto"):
            r = by.get(asked)
            if r is None:
                row += ["–", "–"] + (["–", "–", "–"] if asked == "auto" else [])
                continue
            alpha = r["settings"]["lgh_alpha"]       # None: every VPL its own light (no α)
            row += [f"{_pct3(r['rel_rmse'])} ({'every VPL' if alpha is None else f'α {alpha:g}'})",
                    f"{r['speedup']:.1f}×"]
            if asked == "auto":
                met = r["rel_rmse"] <= err and r["speedup"] >= speed
                est = "–" if r["estimated_rel_rmse"] is None else \
                    _estimate(r["estimated_rel_rmse"], r["estimated_interval"]) + \
                    ("" if r["estimate_holds"] else " **misses**")
                row += [r["settings"]["lgh_split"], est, "yes" if met else "**no**"]
        rows.append(row)
    return _table(["stage", "split", "VPLs", "pixels", "none: rel. RMSE", "none: speed-up", "normal: rel. RMSE",
                   "normal: speed-up", "auto: rel. RMSE", "auto: speed-up", "auto chose", "auto: estimate [95 %]",
                   f"auto: ≤ {100 * err:g} %, ≥ {speed:g}×"], rows)


def lgh_pathtrace_rows(data: dict) -> list[str]:
    """``tools/lgh_pathtrace.py --json``: per suite stage, ``--gi lgh`` against Mitsuba (issue 37 item 4: ``color``
    and ``indirect``, the reference's own noise) and, where a run measured it, the frame's estimate of its error
    against the error measured against brute force (item 5)."""
    rows: dict = {}
    for run in data["runs"]:
        for r in run["output"]["rows"]:
            rows.setdefault(r["stage"], {}).update(r)
    tol = data["runs"][0]["output"]
    out = []
    for name, r in sorted(rows.items(), key=lambda kv: (int(_stage(kv[0]).rsplit("_s", 1)[1]) % 2 == 0, kv[0])):
        seed = int(_stage(name).rsplit("_s", 1)[1])
        row = [_stage(name), "report" if seed % 2 else "tune"]
        if "color_ratio" in r:
            met = abs(r["color_ratio"] - 1) <= tol["mean_tolerance"] \
                and r["color_block_error"] <= tol["block_tolerance"]
            row += ["×".join(map(str, r["resolution"])), f"{r['color_ratio']:.3f}", _pct(r["color_block_error"]),
                    f"{r['indirect_ratio']:.3f}", _pct(r["indirect_block_error"]),
                    f"{_pct(r['color_ref_noise'])} / {_pct(r['color_ref_block_noise'])}", "yes" if met else "**no**"]
        else:
            row += ["–"] * 7
        if "measured_rel_rmse" in r:
            row += [f"{r['vpls']:,}", _pct3(r["measured_rel_rmse"]),
                    _estimate(r["estimated_rel_rmse"], r["estimated_interval"]),
                    "yes" if r["interval_holds"] else "**no**"]
        else:
            row += ["–"] * 4
        out.append(row)
    return _table(["stage", "split", "pixels", "color mean", "color block error", "indirect mean",
                   "indirect block error", "reference noise", "color target met", "VPLs", "measured rel. RMSE",
                   "estimate [95 %]", "holds"], out)


def cache_rows(data: dict) -> list[str]:
    """``tools/cache_bench.py --json``: each stage's array in memory and on disk, its coding and loading
    against the raw words, and a first render with an empty cache, voxel against exact."""
    rows = []
    for run in _runs(data):
        for st in run["output"]["stages"]:
            first = st.get("first_render_seconds")
            for a in st["arrays"]:
                rows.append([_stage(st["stage"]), f"{a['set_bits'] / 1e6:.0f} M",
                             f"{a['dense_bytes'] / 2 ** 20:.0f} MiB", f"{a['disk_bytes'] / 2 ** 20:.1f} MiB",
                             f"{a['encode_seconds']:.2f}",
                             f"{a['load_seconds']:.2f} ({a['read_inflate_seconds']:.2f} + {a['decode_seconds']:.2f})",
                             f"{a['raw_load_seconds']:.2f}", f"{a['load_vs_raw']:.2f}×",
                             f"{first['voxel']:.1f} / {first['exact']:.1f} ({st['first_render_voxel_vs_exact']:.1f}×)"
                             if first else "–"])
    return _table(["stage", "set bits", "in memory", "on disk", "encode s", "load s (read + inflate, decode)",
                   "raw words s", "load vs raw", "first render s, voxel / exact"], rows)


def command_timing(data: dict) -> list[str]:
    """``tools/command_timing.py --json``: a render command as a user runs it, per backend and cache state: the
    command's seconds (and CPU seconds), its frames' and the speed-ups over exact's run, on the machine the data
    names."""
    rows = []
    for run in _runs(data):
        m = run["output"]["machine"]
        for r in run["output"]["runs"]:
            first, *later = r["frame_seconds"]
            ratio = {k: f"{r[k + '_speedup_vs_exact']:.1f}×" if k + "_speedup_vs_exact" in r else "1×"
                     for k in ("command", "cpu", "later_frames")}
            rows.append([f"`{r['visibility']}`", r["cache"], f"{r['seconds']:.1f} ({r['cpu_seconds']:.1f})",
                         f"{first:.1f}; " + ", ".join(f"{s:.1f}" for s in later),
                         f"{ratio['command']} ({ratio['cpu']})", ratio["later_frames"],
                         f"{m['cpu']}, {m['cores']} cores, {m['vector']}; {r['load_average']:.1f}"])
    return _table(["backend", "cache", "command s (CPU s)", "frame s (first; later)", "vs exact, command (CPU s)",
                   "vs exact, later frames", "machine; load average before the run"], rows)


def material_cost(data: dict) -> list[str]:
    """``tools/material_cost.py --json``: per backend (and voxel instruction set), the diffuse and the glossy frame's
    seconds (shading in brackets) and their ratio, with the run's city, BLAS threads and machine."""
    rows = []
    for run in _runs(data):
        out = run["output"]
        m = out["machine"]
        city = f"{out['triangles']:,} triangles, {out['lights']:,} lights"
        for r in out["rows"]:
            w, h = r["diffuse"]["resolution"]
            d, g = r["diffuse"], r["glossy"]
            rows.append([f"{city}, {w}×{h}", f"`{r['visibility']}`" + (f" {r['kernel']}" if r["kernel"] else ""),
                         f"{d['seconds']:.2f} ({d['shading_seconds']:.2f})",
                         f"{g['seconds']:.2f} ({g['shading_seconds']:.2f})", f"{r['glossy_over_diffuse']:.2f}×",
                         out.get("openblas_num_threads") or "default",
                         f"{m['cpu']}, {m['cores']} cores, {m['vector']}; {m['load_average'][0]:.1f}"])
    return _table(["frame", "backend", "diffuse s (shading)", "glossy s (shading)", "glossy / diffuse",
                   "BLAS threads", "machine; load average after the run"], rows)


RENDERERS = {
    "voxel-matrix": voxel_rows, "voxel-faceted": voxel_rows, "voxel-alg5": voxel_alg5,
    "light-scaling": light_scaling, "gi-lgh": gi_lgh, "lgh-build": lgh_build, "gi-reference": gi_reference,
    "anti-aliasing": anti_aliasing, "bench": bench, "dome-error": dome_error, "voxel-kernels": voxel_kernels,
    "frame-speed": frame_speed, "svo": svo_rows, "svo-rebuild": svo_rebuild, "svo-kernels": voxel_kernels,
    "gi-svo": gi_svo, "insm": insm_rows, "insm-dynamic": insm_dynamic, "insm-frame": frame_speed,
    "direct-lgh": direct_lgh, "direct-compare": direct_compare, "direct-frame": direct_frame, "cache": cache_rows,
    "budget": budget_rows, "lgh-suite": lgh_suite_rows,
    "lgh-suite-pt": lgh_pathtrace_rows, "lgh-split": lgh_split_rows, "readme-render": command_timing,
    "materials-cost": material_cost,
}


# ---------------------------------------------------------------------------------------------- figures

# A figure in prose: NAME -> (data file under docs/data/, path into its JSON, format). A path is keys and
# list indexes joined by dots; ``[key=value,...]`` picks the first list item whose fields print as those
# values. A format is a kind and its decimals: ``x2`` 11.65×, ``p1`` 8.2 % (of a fraction), ``s1`` 3.3 s,
# ``n0`` 417, ``c0`` 7,348,425, ``M0`` 149 M/s (of queries per second), ``B1`` 14.0 MiB (of bytes). Name each figure for what it measures, so that
# one quantity measured two ways reads as two names.
_MATRIX = "voxel-matrix", "runs.0.output.[stage=stages/city.usda,voxel_resolution={},direction_step={}].{}"
# tools/cache_bench.py's fields by figure: (path in a stage's output, format)
_CACHE = {"disk": ("arrays.0.disk_bytes", "B1"), "dense": ("arrays.0.dense_bytes", "B0"),
          "load-s": ("arrays.0.load_seconds", "s2"), "raw-s": ("arrays.0.raw_load_seconds", "s2"),
          "load-vs-raw": ("arrays.0.load_vs_raw", "x2"), "first-voxel-s": ("first_render_seconds.voxel", "s1"),
          "first-exact-s": ("first_render_seconds.exact", "s1"), "first-vs-exact": ("first_render_voxel_vs_exact", "x1"),
          "build-s": ("arrays.0.build_seconds", "s1")}
_UNSEEN = "runs.{}.output.[stage=/tmp/uc/unseen_city_1.usda,{}].{}"
FIGURES: dict[str, tuple[str, str, str]] = {
    # --error-budget on a generated city (tools/make_city.py --seed 1): voxel alone and under 0.003
    "unseen-voxel-eps-v": ("budget", _UNSEEN.format(0, "visibility=voxel,budget=1.0", "eps_v"), "p1"),
    "unseen-voxel-budget-eps-v": ("budget", _UNSEEN.format(0, "visibility=voxel,budget=0.003", "eps_v"), "p2"),
    "unseen-voxel-budget-frame-vs-exact": ("budget", _UNSEEN.format(2, "budget=0.003", "frame_speedup"), "x1"),
    "unseen-voxel-budget-cold-vs-exact": ("budget", _UNSEEN.format(3, "budget=0.003", "cold_speedup"), "x1"),
    # the city's voxel speed, three measures: bench queries, voxel_table's query set, a whole frame
    "city-voxel-bench-vs-exact": ("bench", "runs.0.output.[backend=voxel].speedup_vs_exact", "x2"),
    "city-voxel-bench-vs-embree": ("bench", "runs.0.output.[backend=voxel].speedup_vs_bare_embree", "x2"),
    "planes-voxel-bench-vs-exact": ("bench", "runs.1.output.[backend=voxel].speedup_vs_exact", "x2"),
    "planes-voxel-bench-vs-embree": ("bench", "runs.1.output.[backend=voxel].speedup_vs_bare_embree", "x2"),
    "city-svo-bench-vs-exact": ("bench", "runs.2.output.[backend=svo].speedup_vs_exact", "x2"),
    "city-voxel-matrix-32-6-vs-exact": (_MATRIX[0], _MATRIX[1].format(32, 6.0, "speedup_vs_exact"), "x1"),
    "city-voxel-matrix-32-6-qps": (_MATRIX[0], _MATRIX[1].format(32, 6.0, "queries_per_second"), "M0"),
    "city-voxel-matrix-128-2-vs-exact": (_MATRIX[0], _MATRIX[1].format(128, 2.0, "speedup_vs_exact"), "x1"),
    "city-voxel-matrix-128-2-qps": (_MATRIX[0], _MATRIX[1].format(128, 2.0, "queries_per_second"), "M0"),
    "city-voxel-matrix-128-2-eps-v": (_MATRIX[0], _MATRIX[1].format(128, 2.0, "eps_v"), "p2"),
    "city-voxel-matrix-128-2-eps-s": (_MATRIX[0], _MATRIX[1].format(128, 2.0, "eps_s"), "p2"),
    "city-voxel-frame-vs-exact": ("frame-speed", "runs.0.output.0.voxel_speedup_vs_exact", "x1"),
    # the README's render command as written (320 px, 4 rays per pixel, frames 1:3), exact and voxel, whole commands
    **{f"city-readme-voxel-{name}-vs-exact": ("readme-render", f"runs.0.output.runs.[visibility=voxel,cache={cache}]"
                                                               f".{field}_speedup_vs_exact", "x1")
       for name, cache, field in (("command", "full", "command"), ("first-command", "empty", "command"),
                                  ("later-frames", "full", "later_frames"))},
    "city-voxel-matrix-128-6-build-s": (_MATRIX[0], _MATRIX[1].format(128, 6.0, "build_seconds"), "s1"),
    "city-voxel-matrix-128-2-build-s": (_MATRIX[0], _MATRIX[1].format(128, 2.0, "build_seconds"), "s0"),
    # Alg. 5 against Alg. 1 on the creature (the per-frame array's rebuild)
    "creature-voxel-alg5-rebuild-speedup": ("voxel-alg5", "rows.0.bench.output.[backend=voxel].rebuild_speedup", "x0"),
    # the compiled voxel kernel, one thread and two
    "city-avx512-ns": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx512].ns_per_query_one_thread", "n1"),
    "city-avx512-qps": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx512].queries_per_second", "M0"),
    "city-avx2-ns": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx2].ns_per_query_one_thread", "n1"),
    "city-avx2-qps": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx2].queries_per_second", "M0"),
    "city-scalar-ns": ("voxel-kernels", "runs.0.output.rows.[kernel=native-scalar].ns_per_query_one_thread", "n1"),
    "city-warp-ns": ("voxel-kernels", "runs.0.output.rows.[kernel=warp].ns_per_query_one_thread", "n1"),
    "city-avx512-agreement": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx512].agreement_with_warp", "p3"),
    "city-avx2-agreement": ("voxel-kernels", "runs.0.output.rows.[kernel=native-avx2].agreement_with_warp", "p3"),
    "city-scalar-agreement": ("voxel-kernels", "runs.0.output.rows.[kernel=native-scalar].agreement_with_warp", "p3"),
    # the sparse voxel octree
    "city-svo-256-eps-v": ("svo", "runs.1.output.eps_v", "p2"),
    "city-svo-256-eps-s": ("svo", "runs.1.output.eps_s", "p2"),
    "city-svo-256-build-s": ("svo", "runs.1.output.tree_build_seconds", "s1"),
    "city-svo-512-eps-v": ("svo", "runs.2.output.eps_v", "p2"),
    "city-svo-512-eps-s": ("svo", "runs.2.output.eps_s", "p2"),
    "city-svo-512-build-s": ("svo", "runs.2.output.tree_build_seconds", "s1"),
    "city-svo-512-compare-vs-exact": ("svo", "runs.2.output.speedup", "x1"),
    "park-svo-256-eps-v": ("svo", "runs.4.output.eps_v", "p1"),
    "park-svo-256-eps-s": ("svo", "runs.4.output.eps_s", "p1"),
    "cornell-svo-128-eps-v": ("svo", "runs.6.output.eps_v", "p1"),
    "city-svo-256-wrongly-visible": ("svo", "runs.1.output.wrongly_visible", "p2"),
    "city-svo-256-hidden-far": ("svo", "runs.1.output.wrongly_hidden_far", "p2"),
    "city-svo-256-hidden-near": ("svo", "runs.1.output.wrongly_hidden_near", "p2"),
    "park-voxel-alg5-eps-v": ("voxel-alg5", "rows.3.compare.output.eps_v", "p1"),
    "park-voxel-alg5-eps-s": ("voxel-alg5", "rows.3.compare.output.eps_s", "p1"),
    "park-svo-bench-vs-exact": ("svo-rebuild", "runs.0.output.[backend=svo].speedup_vs_exact", "x2"),
    "creature-svo-bench-vs-exact": ("svo-rebuild", "runs.1.output.[backend=svo].speedup_vs_exact", "x2"),
    "city-svo-scalar-ns": ("svo-kernels", "runs.0.output.rows.[kernel=native-scalar].ns_per_query_one_thread", "n0"),
    "city-svo-warp-ns": ("svo-kernels", "runs.0.output.rows.[kernel=warp].ns_per_query_one_thread", "n0"),
    "city-svo-avx512-differing": ("svo-kernels", "runs.0.output.rows.[kernel=native-avx512].differing_answers", "c0"),
    "city-svo-kernel-queries": ("svo-kernels", "runs.0.output.rows.[kernel=native-avx512].queries", "c0"),
    "park-svo-rebuild-s": ("svo-rebuild", "runs.0.output.[backend=svo].rebuild_seconds", "s2"),
    "creature-svo-rebuild-s": ("svo-rebuild", "runs.1.output.[backend=svo].rebuild_seconds", "s2"),
    # intermediate shadow maps at the paper's settings (K 10, w 128, S 512), and the city's frame
    "dragon-insm-paper-eps-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_resolution=128,"
                                "insm_light_resolution=512,insm_count=10].eps_s", "p2"),
    "city-insm-paper-eps-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_resolution=128,"
                              "insm_light_resolution=512,insm_count=10].eps_s", "p2"),
    "dragon-insm-w256-eps-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_resolution=256].eps_s",
                               "p2"),
    "dragon-insm-w256-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_resolution=256].frame_seconds",
                           "s1"),
    "dragon-insm-w256-exact-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_resolution=256]"
                                 ".exact_seconds", "s2"),
    "dragon-insm-w32-eps-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_resolution=32].eps_s", "p1"),
    "dragon-insm-s128-eps-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_light_resolution=128].eps_s", "p2"),
    "dragon-insm-s1024-eps-s": ("insm", "runs.0.output.rows.[stage=stages/dragon.usda,insm_light_resolution=1024].eps_s", "p2"),
    "city-insm-w32-eps-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_resolution=32].eps_s", "p2"),
    "city-insm-w256-eps-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_resolution=256].eps_s", "p2"),
    "city-insm-s128-eps-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_light_resolution=128].eps_s", "p2"),
    "city-insm-k6-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_count=6].frame_seconds", "s1"),
    "city-insm-k10-s": ("insm", "runs.0.output.rows.[stage=stages/city.usda,insm_resolution=128,insm_light_resolution=512,insm_count=10].frame_seconds", "s1"),
    "park-insm-moving-s": ("insm-dynamic", "runs.0.output.dynamic.0.moving_seconds", "s2"),
    "park-insm-still-s": ("insm-dynamic", "runs.0.output.dynamic.0.still_seconds", "s2"),
    "park-insm-moving-over-still": ("insm-dynamic", "runs.0.output.dynamic.0.moving_over_still", "n2"),
    "city-insm-frame-s": ("insm-frame", "runs.0.output.0.insm.seconds", "s1"),
    "city-insm-frame-exact-s": ("insm-frame", "runs.0.output.0.exact.seconds", "s1"),
    "city-insm-frame-voxel-s": ("insm-frame", "runs.0.output.0.voxel.seconds", "s2"),
    "city-insm-frame-vs-exact": ("insm-frame", "runs.0.output.0.insm_speedup_vs_exact", "x2"),
    "city-insm-frame-voxel-vs-exact": ("insm-frame", "runs.0.output.0.voxel_speedup_vs_exact", "x0"),
    # --direct lgh on the city at night (100,000 lamps, 256 px, every pixel both ways)
    "city-night-lgh-frame-s": ("direct-compare", "runs.0.output.seconds.lgh", "s1"),
    "city-night-all-frame-s": ("direct-compare", "runs.0.output.seconds.all", "s0"),
    "city-night-lgh-rel-rmse": ("direct-compare", "runs.0.output.rel_rmse", "p1"),
    # LGH GI against brute force (gi-lgh), and against independent references (gi-reference)
    "cornell-gi-lgh-96-k4-s0-rel-rmse": ("gi-lgh", "runs.0.output.rows.[start_level=0].rel_rmse", "p1"),
    "cornell-gi-lgh-256-k4-rel-rmse": ("gi-lgh", "runs.1.output.rows.[shadow_samples=4].rel_rmse", "p1"),
    "cornell-gi-lgh-256-k64-rel-rmse": ("gi-lgh", "runs.1.output.rows.[shadow_samples=64].rel_rmse", "p2"),
    "city-gi-lgh-a4-k512-rel-rmse": ("gi-lgh", "runs.3.output.rows.[shadow_samples=512].rel_rmse", "p1"),
    "city-gi-lgh-a3-k768-rel-rmse": ("gi-lgh", "runs.4.output.rows.[shadow_samples=768].rel_rmse", "p1"),
    "city-gi-lgh-a3-k1024-rel-rmse": ("gi-lgh", "runs.4.output.rows.[shadow_samples=1024].rel_rmse", "p1"),
    "city-gi-lgh-voxel-k64-rel-rmse": ("gi-lgh", "runs.5.output.rows.[shadow_samples=64].rel_rmse", "p1"),
    "city-gi-lgh-voxel-k512-rel-rmse": ("gi-lgh", "runs.5.output.rows.[shadow_samples=512].rel_rmse", "p1"),
    "box-bruteforce-energy": ("gi-reference", "runs.0.output.methods.vpl-bruteforce.indirect_ratio", "n3"),
    "box-lgh-energy": ("gi-reference", "runs.0.output.methods.lgh.indirect_ratio", "n3"),
    "city-gi-bruteforce-s": ("gi-lgh-city-compiled", "bruteforce_seconds", "s0"),
    # --gi svo against brute force on cornell at 256 px, svo rays and exact rays
    "cornell-gi-svo-512-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=512].rays.svo.rel_rmse", "p1"),
    "cornell-gi-svo-1024-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=1024].rays.svo.rel_rmse", "p1"),
    "cornell-gi-svo-2048-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=2048].rays.svo.rel_rmse", "p1"),
    "cornell-gi-svo-512-exact-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=512].rays.exact.rel_rmse", "p1"),
    "cornell-gi-svo-1024-exact-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=1024].rays.exact.rel_rmse", "p1"),
    "cornell-gi-svo-2048-exact-rel-rmse": ("gi-svo", "runs.0.output.rows.[vpls=2048].rays.exact.rel_rmse", "p1"),
    # LGH GI on the city, compiled gather (100k VPLs, 256 px, alpha 4, k 512, brute force in the same run)
    "city-gi-lgh-compiled-speedup": ("gi-lgh-city-compiled", "rows.0.speedup", "x0"),
    "city-gi-lgh-compiled-rel-rmse": ("gi-lgh-city-compiled", "rows.0.rel_rmse", "p1"),
    # a glossy clearcoated preview surface on every mesh of a generated city against its diffuse frame
    # (tools/material_cost.py): run 0 as the machine is, run 1 with one BLAS thread, run 2 the same on a quieter machine
    **{f"city-glossy-{name}-cost": ("materials-cost", f"runs.{run}.output.rows.[{pick}].glossy_over_diffuse", "x2")
       for name, run, pick in (("exact", 0, "visibility=exact"), ("voxel-avx2", 0, "kernel=native-avx2"),
                               ("voxel-scalar", 0, "kernel=native-scalar"), ("exact-blas1", 1, "visibility=exact"),
                               ("voxel-avx2-blas1", 1, "kernel=native-avx2"), ("exact-quiet", 2, "visibility=exact"),
                               ("voxel-avx2-quiet", 2, "kernel=native-avx2"),
                               ("voxel-scalar-quiet", 2, "kernel=native-scalar"))},
    # the voxel cache at 128³ / 2° (tools/cache_bench.py)
    **{f"{name}-cache-{what}": ("cache", f"runs.0.output.stages.[stage=stages/{name}.usda].{_CACHE[what][0]}",
                                _CACHE[what][1])
       for name, whats in (("cornell", ("dense", "disk", "load-s", "raw-s", "first-voxel-s", "first-exact-s",
                                        "first-vs-exact", "build-s")),
                           ("city", ("disk", "load-s", "raw-s", "load-vs-raw")))
       for what in whats},
}

_FORMATS = {
    "x": lambda v, n: f"{v:.{n}f}×", "p": lambda v, n: f"{100 * v:.{n}f} %", "s": lambda v, n: f"{v:.{n}f} s",
    "n": lambda v, n: f"{v:.{n}f}", "c": lambda v, n: f"{v:,.{n}f}", "M": lambda v, n: f"{v / 1e6:.{n}f} M/s",
    "B": lambda v, n: f"{v / 2 ** 20:.{n}f} MiB",
}
_STEP = re.compile(r"\[[^\]]*\]|[^.\[]+")


def lookup(data, path: str):
    """The value at ``path`` (keys, indexes and ``[key=value,...]`` picks; see ``FIGURES``) in ``data``."""
    x = data
    for step in _STEP.findall(path):
        if step.startswith("["):
            want = dict(kv.split("=", 1) for kv in step[1:-1].split(","))
            x = next(i for i in x if all(str(i.get(k)) == v for k, v in want.items()))
        elif isinstance(x, list):
            x = x[int(step)]
        else:
            x = x[step]
    return x


def figure(name: str) -> str:
    """The text of figure ``name`` as its data says."""
    if name not in FIGURES:
        raise SystemExit(f"bench_tables: unknown figure {name!r} (add it to FIGURES in tools/bench_tables.py)")
    table, path, fmt = FIGURES[name]
    try:
        value = lookup(load(table), path)
    except (KeyError, IndexError, StopIteration, ValueError, TypeError) as e:
        raise SystemExit(f"bench_tables: figure {name!r}: no {path!r} in docs/data/{table}.json ({e!r})")
    return _FORMATS[fmt[0]](value, int(fmt[1:]))


# A measured figure stated in prose: a number and a unit of time, speed or error (not 4×4, a size).
MEASURED = re.compile(r"(?<![\w.])\d[\d,.]*(?:\s?[–-]\s?\d[\d,.]*)?\s?"
                      r"(?:×(?!\s?\d)|%|(?:s|ms|µs|ns|M/s|minutes?|hours?)\b)")
# A figure that is not a measurement: one a paper reports, a value chosen, one worked out (see above).
GIVEN = re.compile(r"<!-- (paper|set|calc) -->(?P<body>[^<\n]*)<!-- /\1 -->")
# The measured figures a section may state outside markers, (page, heading) -> count: none anywhere (a
# section may be given a count here while its figures are being tied).
UNTIED: dict[tuple[str, str], int] = {}


def untied(text: str) -> list[tuple[int, str, str]]:
    """(line, figure, ``##`` section) of each measured figure outside tables, code and markers."""
    text = MARKER.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    text = GIVEN.sub("", FIG.sub("", text))
    found, fenced, section = [], False, ""
    for no, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced and line.startswith("## "):
            section = line[3:].strip()
        if fenced or line.lstrip().startswith("|"):
            continue
        line = re.sub(r"`[^`]*`", "", line)
        found += [(no, m.group(0), section) for m in MEASURED.finditer(line)]
    return found


def misgiven(text: str) -> list[tuple[int, str]]:
    """(line, marker) of each paper/set/calc marker that does not hold exactly one figure."""
    return [(text.count("\n", 0, m.start()) + 1, m.group(0)) for m in GIVEN.finditer(text)
            if len(MEASURED.findall(m.group("body"))) != 1]


# ------------------------------------------------------------------------------------------------ pages


def load(name: str) -> dict:
    path = DATA / f"{name}.json"
    if not path.exists():
        raise SystemExit(f"bench_tables: no data for table {name!r} ({path.relative_to(ROOT)})")
    return json.loads(path.read_text())


def block(name: str) -> str:
    """What goes between the markers of table ``name``: the table, then where its figures come from."""
    if name not in RENDERERS:
        raise SystemExit(f"bench_tables: unknown table {name!r}; known: {', '.join(RENDERERS)}")
    data = load(name)
    lines = RENDERERS[name](data) + [""]
    runs = _runs(data)
    lines.append(f"Data `docs/data/{name}.json`, from:")
    lines.append("")
    for run in runs:
        note = f"; {run['note']}" if run.get("note") else ""
        lines.append(f"- `{run['command']}` ({run['source']}{note})")
    return "\n".join(lines) + "\n"


def render_page(text: str) -> str:
    text = MARKER.sub(lambda m: m.group(1) + block(m.group("name")) + m.group(4), text)
    return FIG.sub(lambda m: m.group(1) + figure(m.group("name")) + m.group(4), text)


def pages() -> list[Path]:
    """Every page whose tables and figures come from the data: README.md and docs/*.md (not the changelog)."""
    return [ROOT / "README.md"] + sorted(p for p in DOCS.glob("*.md") if p != CHANGELOG)


def rewrite(check: bool) -> int:
    stale = 0
    placed = {m.group("name") for page in pages() for m in MARKER.finditer(page.read_text())}
    unplaced = sorted(set(RENDERERS) - placed)
    if unplaced:
        print(f"bench_tables: no page has a marker for {', '.join(unplaced)}", file=sys.stderr)
    used = {m.group("name") for page in pages() for m in FIG.finditer(page.read_text())}
    unused = sorted(set(FIGURES) - used)
    if unused:
        print(f"bench_tables: no page states figure {', '.join(unused)}", file=sys.stderr)
    loose = 0
    for page in pages():
        rel = str(page.relative_to(ROOT))
        found = untied(page.read_text())
        for section in dict.fromkeys(s for _, _, s in found):
            figs = [(no, fig) for no, fig, s in found if s == section]
            allowed = UNTIED.get((rel, section), 0)
            if len(figs) > allowed:
                loose += 1
                print(f"bench_tables: {rel} ({section or 'top'}) states {len(figs)} measured figure(s) outside "
                      f"<!-- fig --> markers, {allowed} allowed (tie them to docs/data, move a one-off result to "
                      f"docs/CHANGELOG.md, or mark a paper's or chosen figure; see --untied):", file=sys.stderr)
                for no, fig in figs:
                    print(f"  {rel}:{no}: {fig}", file=sys.stderr)
        for no, marker in misgiven(page.read_text()):
            loose += 1
            print(f"bench_tables: {rel}:{no}: {marker} must hold exactly one figure", file=sys.stderr)
    for page in pages():
        old = page.read_text()
        new = render_page(old)
        if new == old:
            continue
        if check:
            stale += 1
            rel = str(page.relative_to(ROOT))
            sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), new.splitlines(True), rel, rel + " (from data)"))
        else:
            page.write_text(new)
            print(f"bench_tables: rewrote {page.relative_to(ROOT)}")
    if check and stale:
        print(f"bench_tables: {stale} page(s) out of date; run python tools/bench_tables.py", file=sys.stderr)
    return 1 if unplaced or unused or loose or (check and stale) else 0


# ------------------------------------------------------------------------------------------- re-running


def _argv(command: str) -> list[str]:
    argv = shlex.split(command)
    if argv[0] == "python":
        return [sys.executable] + argv[1:]
    if argv[0] == "usdml":
        return [sys.executable, "-m", "usdml.cli"] + argv[1:]
    return argv


def _json_output(stdout: str):
    """The JSON document a tool printed (anything it printed before it is skipped)."""
    for m in re.finditer(r"^[\[{]", stdout, re.M):
        try:
            return json.JSONDecoder().raw_decode(stdout[m.start():])[0]
        except json.JSONDecodeError:
            continue
    raise ValueError("no JSON in the output")


def rerun(name: str, only: set[int] | None = None, timeout: float | None = None) -> int:
    data = load(name)
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    runs = _runs(data)
    for i, run in enumerate(runs):
        if only is not None and i not in only:
            continue
        print(f"bench_tables: {run['command']}", flush=True)
        try:
            done = subprocess.run(_argv(run["command"]), cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            print(f"bench_tables: {run['command']!r} took over {timeout:g} s; {name} left as it was", file=sys.stderr)
            return 1
        if done.returncode != 0:
            sys.stderr.write(done.stderr)
            print(f"bench_tables: {run['command']!r} exited {done.returncode}; {name} left as it was", file=sys.stderr)
            return 1
        output = _json_output(done.stdout)
        when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
        for same in (r for r in runs if r["command"] == run["command"]):    # a command two rows share
            same["output"] = output
            same["source"] = f"measured at {rev or 'an unknown commit'} on {when}, {os.cpu_count()} CPUs"
            same.pop("note", None)
    (DATA / f"{name}.json").write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n")
    return rewrite(check=False)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    g = p.add_mutually_exclusive_group()
    g.add_argument("--check", action="store_true", help="exit 1 if a table differs from its data")
    g.add_argument("--list", action="store_true", help="print each table's data source and commands")
    g.add_argument("--untied", action="store_true", help="print each measured figure no marker ties to data")
    g.add_argument("--run", metavar="NAME", help="re-measure table NAME (its commands), then rewrite the tables")
    p.add_argument("--commands", metavar="I,J", help="with --run: only these of its commands (numbered from 0)")
    p.add_argument("--timeout", type=float, metavar="S", help="with --run: stop a command after S seconds")
    args = p.parse_args(argv)
    if args.list:
        for name in RENDERERS:
            for i, run in enumerate(_runs(load(name))):
                print(f"{name} {i}: {run['command']}  [{run['source']}]")
        for name, (table, path, _) in FIGURES.items():
            print(f"fig {name}: {figure(name)}  [docs/data/{table}.json {path}]")
        return 0
    if args.untied:
        for page in pages():
            for no, fig, section in untied(page.read_text()):
                print(f"{page.relative_to(ROOT)}:{no}: {fig}  ({section})")
        return 0
    if args.run:
        only = None if args.commands is None else {int(i) for i in args.commands.split(",")}
        return rerun(args.run, only, args.timeout)
    return rewrite(args.check)


if __name__ == "__main__":
    sys.exit(main())
