"""The ``usdml`` command.

Flags follow usdrecord's names (``--camera``, ``--renderSettingsPrimPath``, ``--frames``,
``--imageWidth``). User mistakes end with one ``usdml: error:`` line and exit status 2; a traceback
means a bug in usdml.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time


def _add_stage_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("stage", help="USD stage to read (.usd, .usda, .usdc, .usdz)")
    p.add_argument("--camera", help="camera prim path or name (default: RenderSettings camera, main_cam, "
                                    "the first camera, else a camera framing the scene)")
    p.add_argument("--renderSettingsPrimPath", dest="render_settings",
                   help="RenderSettings prim (default: the stage's renderSettingsPrimPath metadata)")
    p.add_argument("--purposes", metavar="PURPOSE[,PURPOSE...]",
                   help="imageable purposes to include besides 'default', as usdrecord (default: the "
                        "RenderSettings' includedPurposes, else 'render' -- final-frame geometry; "
                        "'proxy' for usdview's interactive look)")
    p.add_argument("--implicit-detail", type=int, default=10, metavar="N",
                   help="segments around implicit prims (Sphere, Cylinder ...), default 10 as usdImaging")


def _delegate(args: argparse.Namespace):
    from usdml.stage import StageDelegate

    purposes = None if args.purposes is None else args.purposes.replace(",", " ").split()
    return StageDelegate(args.stage, camera=args.camera, render_settings_path=args.render_settings,
                         purposes=purposes, implicit_detail=args.implicit_detail)


def _cmd_info(args: argparse.Namespace) -> int:
    from usdml.info import format_info, stage_info

    started = time.perf_counter()
    delegate = _delegate(args)
    info = stage_info(delegate, args.time, started=started)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(format_info(info))
    return 0


def _settings_overrides(args: argparse.Namespace) -> dict:
    values = {"visibility": getattr(args, "visibility", None), "seed": args.seed,
              "dome_samples": args.dome_samples, "gi": args.gi, "vpl_count": args.vpls,
              "lgh_alpha": args.lgh_alpha, "lgh_levels": args.lgh_levels,
              "shadow_samples": args.shadow_samples, "interleave": args.interleave}
    return {k: v for k, v in values.items() if v is not None}


def _add_lighting_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, help="random seed (VPLs, shadow samples, dome light sampling)")
    p.add_argument("--dome-samples", type=int, metavar="K",
                   help="distant lights each DomeLight is importance-sampled into per frame (default 256)")
    p.add_argument("--gi", choices=["none", "lgh", "vpl-bruteforce"],
                   help="indirect light: VPLs through a lighting grid hierarchy (paper 004), or every VPL "
                        "with exact visibility (reference); default: the stage's usdml:gi, else none")
    p.add_argument("--vpls", type=int, metavar="N", help="virtual point lights per frame (default 100000)")
    p.add_argument("--lgh-alpha", type=float, help="LGH blending radius factor alpha (default 1)")
    p.add_argument("--lgh-levels", type=int, help="LGH levels (default 0 = the paper's rule)")
    p.add_argument("--shadow-samples", type=int, help="stochastic shadow samples per pixel (default 4)")
    p.add_argument("--interleave", type=int, choices=[1, 2, 4], help="interleaved sampling tile size (default 1)")


def _cmd_render(args: argparse.Namespace) -> int:
    from usdml.render.sequence import RenderJob, render_sequence

    job = RenderJob(stage=args.stage, output=args.output, frames=args.frames, camera=args.camera,
                    image_width=args.imageWidth, render_settings=args.render_settings,
                    purposes=None if args.purposes is None else args.purposes.replace(",", " ").split(),
                    implicit_detail=args.implicit_detail, camera_light=args.cameraLightEnabled,
                    aovs=[a for spec in args.aovs or [] for a in spec.split(",") if a] or None,
                    device=args.device, resume=args.resume, preview=args.preview,
                    overrides=_settings_overrides(args))
    if job.image_width is not None and not 1 <= job.image_width <= 16384:
        from usdml.errors import UsdmlError
        raise UsdmlError(f"--imageWidth {job.image_width}: use 1 to 16384 pixels")
    summary = render_sequence(job)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    done = len(summary["frames"])
    res = "x".join(map(str, summary["resolution"]))
    print(f"rendered {done} frame(s) at {res} with {summary['visibility']} visibility: "
          f"{summary['secondsPerFrame']:.2f} s/frame, {summary['seconds']:.1f} s in all"
          + (f"; {len(summary['skipped'])} frame(s) already complete, skipped" if summary["skipped"] else ""))
    for path in summary["outputs"]:
        print(f"  {path}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from usdml.bench import bench_visibility, format_bench

    results = bench_visibility(_delegate(args), backends=args.visibility or ["exact"],
                               image_width=args.imageWidth, frame=args.frame)
    print(json.dumps(results, indent=2) if args.json else format_bench(results))
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from usdml.compare import compare_gi
    from usdml.errors import UsdmlError

    if args.visibility:
        raise UsdmlError("--visibility comparisons need an approximate visibility backend; only exact exists yet")
    if not args.gi:
        raise UsdmlError("give --gi METHOD (and --against METHOD) to compare")
    overrides = {k: v for k, v in _settings_overrides(args).items() if k != "gi"}
    result = compare_gi(_delegate(args), args.gi, args.against or "vpl-bruteforce", args.frame,
                        args.imageWidth, args.device, args.png, overrides)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        s = result["seconds"]
        print(f"{result['gi']} vs {result['against']} on {result['pixels']:,} pixels, {result['vpls']:,} VPLs: "
              f"relative RMSE of indirect {100 * result['rel_rmse']:.2f} %; indirect pass "
              f"{s[result['gi']]:.2f} s vs {s[result['against']]:.2f} s ({result['speedup']:.1f}x)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="usdml", description="Render USD stages with thousands of lights.")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="do not print warnings")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    info = sub.add_parser("info", help="summarize what usdml reads from a stage")
    _add_stage_args(info)
    info.add_argument("--time", type=float, help="timecode to inspect (default: the stage's startTimeCode)")
    info.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    info.set_defaults(run=_cmd_info)

    render = sub.add_parser("render", help="render timecodes to multi-channel OpenEXR (AOVs)")
    _add_stage_args(render)
    render.add_argument("output", nargs="?", help="output EXR path; '#' marks the frame number "
                        "(out.####.exr); default: the RenderSettings products")
    render.add_argument("--frames", help="FrameSpec as usdrecord: 1:48, 1:10x2, 1,5,9 (default: the start frame)")
    render.add_argument("--imageWidth", type=int, help="image width in pixels (height from the aspect ratio)")
    render.add_argument("--visibility", help="visibility backend (default: the stage's usdml:visibility, else exact)")
    render.add_argument("--aovs", action="append", help="comma-separated AOVs to write (default: color, direct, indirect, "
                        "shadow, depth, normal, P, albedo, primId, instanceId)")
    render.add_argument("--device", default="cpu", help="cpu or cuda (Warp kernels)")
    _add_lighting_args(render)
    render.add_argument("--resume", action="store_true", help="skip frames whose files are already complete")
    render.add_argument("--preview", action="store_true", help="also write a PNG of the color AOV beside each EXR")
    render.add_argument("--disableCameraLight", action="store_false", dest="cameraLightEnabled",
                        help="no camera light for stages without lights (usdrecord's flag)")
    render.add_argument("--json", action="store_true", help="print the summary as JSON")
    render.set_defaults(run=_cmd_render)

    compare = sub.add_parser("compare", help="one frame two ways: error of a method against its reference")
    _add_stage_args(compare)
    compare.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    compare.add_argument("--visibility", help="approximate visibility backend to compare against exact")
    compare.add_argument("--against", help="reference method (default: vpl-bruteforce for --gi)")
    compare.add_argument("--imageWidth", type=int, default=128, help="image width (default 128)")
    compare.add_argument("--device", default="cpu", help="cpu or cuda")
    compare.add_argument("--png", metavar="PREFIX", help="write PREFIX_direct/indirect/color.png")
    compare.add_argument("--json", action="store_true", help="print JSON")
    _add_lighting_args(compare)
    compare.set_defaults(run=_cmd_compare)

    bench = sub.add_parser("bench", help="time the visibility queries of one frame")
    _add_stage_args(bench)
    bench.add_argument("--visibility", action="append", help="backend to time (repeat for several; default exact)")
    bench.add_argument("--imageWidth", type=int, default=512, help="image width in pixels (default 512)")
    bench.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    bench.add_argument("--json", action="store_true", help="print JSON")
    bench.set_defaults(run=_cmd_bench)
    return parser


class _OneLine(logging.Handler):
    """``usdml: warning: ...`` on whatever ``sys.stderr`` is when the record is emitted."""

    def emit(self, record: logging.LogRecord) -> None:
        print(f"usdml: {record.levelname.lower()}: {record.getMessage()}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from usdml import __version__

        print(f"usdml {__version__}")
        return 0
    if not getattr(args, "run", None):
        parser.print_help()
        return 2
    log = logging.getLogger("usdml")
    log.handlers[:] = [_OneLine()]
    log.setLevel(logging.ERROR if args.quiet else logging.WARNING)
    log.propagate = False

    from usdml.errors import UsdmlError

    try:
        return args.run(args)
    except UsdmlError as e:
        print(f"usdml: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("usdml: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":
    sys.exit(main())
