"""The ``usdml`` command.

Flags follow usdrecord's names (``--camera``, ``--renderSettingsPrimPath``, ``--frames``,
``--imageWidth``). User mistakes end with one ``usdml: error:`` line and exit status 2; a traceback
means a bug in usdml.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
import warnings

from usdml.params import (BAKE, BENCH, COMPARE, INFO, RENDER, add_cmdline_args, options_from_args,
                          overrides_from_args, purpose_list)
from usdml.recorder import check_width


class _ArgumentError(Exception):
    """A command line argparse refuses: printed as one ``usdml: error:`` line."""


class _Parser(argparse.ArgumentParser):
    """argparse with no prefix matching (a new flag never rebinds an old script's abbreviation) and
    its refusals raised, so :func:`main` prints them as every other mistake: one line, exit 2, no
    usage dump. Subcommands' parsers are of this class too (``add_subparsers`` uses the parent's)."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        raise _ArgumentError(f"{self.prog}: {message}; see {self.prog} --help")


class _Renamed(argparse.Action):
    """A flag a command no longer takes under this name: refused in one line naming the new one (not an
    alias, where the old name means something else on another command). Hidden from the help."""

    def __init__(self, option_strings, dest, *, new: str, why: str, **kwargs) -> None:
        super().__init__(option_strings, argparse.SUPPRESS, nargs="?", default=argparse.SUPPRESS,
                         help=argparse.SUPPRESS)
        self.new, self.why = new, why

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} is now {self.new} ({self.why}); give {self.new} N")


def _add_quiet_arg(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: not given after the command, the value before it (or False) stays
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="do not print warnings")


def _add_stage_args(p: argparse.ArgumentParser, command: str) -> None:
    p.add_argument("stage", help="USD stage to read (.usd, .usda, .usdc, .usdz)")
    add_cmdline_args(p, command, "camera", "render_settings", "purposes", "implicit_detail")


def _purposes(args: argparse.Namespace) -> list[str] | None:
    """``--purposes`` as a list (comma or space separated), every name a UsdGeom purpose."""
    return purpose_list(args.purposes, "--purposes")


def _delegate(args: argparse.Namespace):
    from usdml.stage import StageDelegate

    return StageDelegate(args.stage, camera=args.camera, render_settings_path=args.render_settings,
                         purposes=_purposes(args), implicit_detail=args.implicit_detail)


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


def _update_over(delegate, backend, frames) -> None:
    """Bring ``backend`` through every frame of ``frames`` (what ``usdml bake`` builds and caches)."""
    from usdml.scene import diff
    from usdml.stage.delegate import require_geometry

    previous = None
    delegate.check_times(frames)
    for f in frames:
        snap = delegate.snapshot(f)
        require_geometry(delegate, snap)
        backend.update(snap, diff(previous, snap))
        previous = snap


def _cmd_bake(args: argparse.Namespace) -> int:
    from usdml.render.sequence import build_messages, frame_spec
    from usdml.visibility import backend_class, make_backend

    delegate = _delegate(args)
    settings = delegate.usdml_settings.updated(**overrides_from_args(args))
    frames = frame_spec(args.frames, delegate.start_time, delegate.end_time)
    skip = backend_class(args.backend).bake_skip(settings)
    if skip:
        print(f"{args.stage} is {skip[0]}", file=sys.stderr)
        if args.json:
            print(json.dumps({"stage": args.stage, "frames": frames, **skip[1]}, indent=2))
        return 0
    t0 = time.perf_counter()
    backend = make_backend(args.backend, settings, args.device, cache=args.cache, **build_messages())
    _update_over(delegate, backend, frames)
    fields, lines, total = backend.baked()
    backend.close()
    summary = {"stage": args.stage, "frames": frames, **fields, "seconds": time.perf_counter() - t0}
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print("\n".join(lines + [f"{total} in {summary['seconds']:.1f} s"]))
    return 0


class _Bakers:
    """``bake --backend``'s choices: the registered backends that declare ``BAKE``, read when argparse asks
    (a backend registered after the parser was made counts; the modules are imported only then)."""

    def _names(self) -> list[str]:
        from usdml.visibility import backend_class, backend_names
        from usdml.visibility.base import BAKE

        return [n for n in backend_names() if backend_class(n).supports(BAKE)]

    def __contains__(self, name) -> bool:
        return name in self._names()

    def __iter__(self):
        return iter(self._names())


def _cmd_view(args: argparse.Namespace) -> int:
    from usdml.errors import UsdmlError
    from usdml.view import view

    try:
        w, h = (int(x) for x in args.window_size.split(","))
    except ValueError:
        raise UsdmlError(f"--window-size {args.window_size!r}: give W,H in pixels, e.g. 1280,720") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise UsdmlError(f"--window-size {w},{h}: use 16 to 8192 pixels a side")
    drawn = view(args.stage, args.png, frame=args.frame, camera=args.camera,
                 show=tuple(s for s in args.show.split(",") if s), window_size=(w, h), interactive=args.interactive,
                 octree_resolution=args.octree_resolution, lgh_level=args.lgh_level)
    print(", ".join(f"{k} {v}" for k, v in drawn.items() if k not in ("stage", "png")) + (f" -> {args.png}" if args.png else ""))
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from usdml.recorder import Recorder

    # the command is the pipeline API (usdml.Recorder): one code path
    recorder = Recorder(_flags=True, **dict(options_from_args(args), purposes=_purposes(args)),
                        **overrides_from_args(args))
    summary = recorder.record_sequence(args.stage, args.frames, args.output, resume=args.resume).summary
    if summary.get("failed"):
        if args.json:
            print(json.dumps(summary, indent=2))
        print(f"usdml: error: {len(summary['failed'])} frame(s) failed ({summary['rerun']}): "
              f"{next(iter(summary['errors'].values()))}; render them again with --frames {summary['rerun']}",
              file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    done = len(summary["frames"])
    res = "x".join(map(str, summary["resolution"]))
    print(f"rendered {done} frame(s) at {res} with {summary['visibility']} visibility: "
          f"{summary['secondsPerFrame']:.2f} s/frame, {summary['seconds']:.1f} s in all"
          + (f"; {len(summary['skipped'])} frame(s) already complete, skipped" if summary["skipped"] else "")
          + (f"; {len(summary['stale'])} stale (other settings), rendered again" if summary["stale"] else ""))
    for f, e in summary.get("estimates", {}).items():
        print(f"frame {f}: estimated eps_v {100 * e['eps_v']:.2f} % [{100 * e['eps_v_lo']:.2f}, "
              f"{100 * e['eps_v_hi']:.2f}], eps_s {100 * e['eps_s']:.2f} % [{100 * e['eps_s_lo']:.2f}, "
              f"{100 * e['eps_s_hi']:.2f}] ({e['pixels']} pixels, {e['queries']:,} exact rays)"
              + (f"; --error-budget {e['budget']:g}: level {e['level']}, {100 * e['refined_fraction']:.1f} % of "
                 f"queries re-asked of exact" if "budget" in e else ""))
    for f, kinds in summary.get("lightingEstimates", {}).items():
        for kind, e in kinds.items():
            if kind == "area":
                print(f"frame {f}: lights with area: estimated rel. RMSE of their sampling {100 * e['rel_rmse']:.2f} % "
                      f"({e['light_samples']} samples a light)")
                continue
            print(f"frame {f}: {kind} LGH vs brute force: estimated rel. RMSE {100 * e['rel_rmse']:.2f} % "
                  f"[{100 * e['rel_rmse_lo']:.2f}, {100 * e['rel_rmse_hi']:.2f}], bias {100 * e['rel_bias']:+.2f} % "
                  f"({e['pixels']} pixels, {e['rays']:,} rays)")
    for path in summary["outputs"] + summary["previews"]:
        print(f"  {path}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from usdml.bench import bench_visibility, format_bench

    from usdml.render.sequence import build_messages

    check_width(args.imageWidth)
    delegate = _delegate(args)
    settings = delegate.usdml_settings.updated(**overrides_from_args(args))
    results = bench_visibility(delegate, backends=args.visibility or ["exact"],
                               image_width=args.imageWidth, frame=args.frame, settings=settings,
                               device=args.device, backend_options=build_messages())
    print(json.dumps(results, indent=2) if args.json else format_bench(results))
    return 0


def _warn_unused(args: argparse.Namespace, mode: str, options: dict) -> None:
    """A ``usdml: warning:`` for each given option (flag -> (its dest, the modes that read it)) that
    ``mode``, the comparison being made, does not read."""
    log = logging.getLogger("usdml")
    for flag, (dest, modes) in options.items():
        if getattr(args, dest) is not None and mode not in modes:
            log.warning(f"{flag} is ignored: it applies to compare {modes} (this comparison: {mode})")


def _cmd_compare(args: argparse.Namespace) -> int:
    from usdml.compare import compare_gi, format_gi_comparison
    from usdml.errors import UsdmlError

    check_width(args.imageWidth)
    mode = "--direct" if args.direct is not None and not args.gi else "--visibility" if args.visibility else "--gi"
    _warn_unused(args, mode, {"--heatmap": ("heatmap", "--visibility"), "--plot": ("plot", "--visibility"),
                              "--png": ("png", "--gi or --direct"), "--reference-pixels": ("reference_pixels", "--direct")})
    if args.direct is not None and not args.gi:       # --visibility: both renders' shadow rays
        from usdml.compare import compare_direct, format_direct_comparison

        overrides = {k: v for k, v in overrides_from_args(args).items() if k != "direct"}
        if args.visibility:
            overrides["visibility"] = args.visibility
        against = args.against or ("all" if args.direct == "lgh" else "lgh")
        r = compare_direct(_delegate(args), args.direct, against, args.frame, args.imageWidth, args.device,
                           args.png, overrides, reference_pixels=args.reference_pixels or 0)
        print(json.dumps(r, indent=2) if args.json else format_direct_comparison(r))
        return 0
    if args.visibility:
        from usdml.compare import compare_visibility, format_visibility_comparison
        from usdml.render.sequence import build_messages

        if args.gi:
            raise UsdmlError("compare one thing at a time: --visibility or --gi")
        overrides = {k: v for k, v in overrides_from_args(args).items() if k != "visibility"}
        r = compare_visibility(_delegate(args), args.visibility, args.against or "exact", args.frame,
                               args.imageWidth, args.device, args.heatmap, overrides, build_messages(),
                               plot=args.plot)
        print(json.dumps(r, indent=2) if args.json else format_visibility_comparison(r))
        return 0
    if not args.gi:
        raise UsdmlError("give --gi METHOD (and --against METHOD), --visibility BACKEND or --direct lgh --against all "
                         "to compare")
    overrides = {k: v for k, v in overrides_from_args(args).items() if k != "gi"}
    result = compare_gi(_delegate(args), args.gi, args.against or "vpl-bruteforce", args.frame,
                        args.imageWidth, args.device, args.png, overrides)
    print(json.dumps(result, indent=2) if args.json else format_gi_comparison(result))
    return 0


def _cmd_cache(args: argparse.Namespace) -> int:
    """``usdml cache [list|clean]``: what the on-disk cache holds (with no action too), and emptying it."""
    from usdml.cache import Cache
    from usdml.errors import UsdmlError

    cache = Cache(args.cache)
    if args.action == "list":
        if args.older_than is not None:
            logging.getLogger("usdml").warning("--older-than is ignored: it applies to usdml cache clean")
        entries = cache.entries()
        total = sum(e.bytes for e in entries)
        if args.json:
            print(json.dumps({"root": str(cache.root), "limit": cache.limit, "bytes": total,
                              "entries": [e.summary() for e in entries]}, indent=2))
            return 0
        for e in entries:
            used = time.strftime("%Y-%m-%d %H:%M", time.localtime(e.last_used))
            what = e.meta.get("source") or ("" if e.format == "USDMLC02" else f"({e.format})")
            print(f"{e.kind:6s} {e.key[:12]}  {e.bytes / 2**20:9.2f} MiB  {used}  {what}")
        print(f"{len(entries)} entr{'y' if len(entries) == 1 else 'ies'}, {total / 2**20:.1f} MiB in {cache.root} "
              f"(limit {cache.limit / 2**30:.2f} GiB, USDML_CACHE_SIZE)")
        return 0
    if args.older_than is not None and not args.older_than >= 0:
        raise UsdmlError(f"--older-than {args.older_than:g}: give a number of days >= 0")
    gone = cache.clean(None if args.older_than is None else args.older_than * 86400.0)
    freed = sum(e.bytes for e in gone)
    if args.json:
        print(json.dumps({"root": str(cache.root), "removed": [e.summary() for e in gone], "bytes": freed}, indent=2))
    else:
        print(f"removed {len(gone)} entr{'y' if len(gone) == 1 else 'ies'}, freed {freed / 2**20:.1f} MiB from {cache.root}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="usdml", description="Render USD stages with thousands of lights.")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="do not print warnings")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    info = sub.add_parser("info", help="summarize what usdml reads from a stage")
    _add_stage_args(info, INFO)
    info.add_argument("--time", type=float, help="timecode to inspect (default: the stage's startTimeCode)")
    info.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    info.set_defaults(run=_cmd_info)

    render = sub.add_parser("render", help="render timecodes to multi-channel OpenEXR (AOVs)")
    _add_stage_args(render, RENDER)
    render.add_argument("output", nargs="?", help="output EXR path; '#' marks the frame number "
                        "(out.####.exr); default: the RenderSettings products")
    render.add_argument("--frames", help="FrameSpec as usdrecord: 1:48, 1:10x2, 1,5,9 (default: the start frame)")
    add_cmdline_args(render, RENDER, "image_width", "aovs", "device")
    add_cmdline_args(render, RENDER)
    render.add_argument("--resume", action="store_true", help="skip frames whose files are already complete")
    add_cmdline_args(render, RENDER, "preview", "camera_light")
    render.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_cmdline_args(render, RENDER, "workers", "scheduler", "chunk_size", "retries", "nthreads")
    render.set_defaults(run=_cmd_render)

    view = sub.add_parser("view", help="a frame in 3-D (pyvista): geometry, instances, cameras, lights, to a PNG")
    view.add_argument("stage", help="USD stage to read (.usd, .usda, .usdc, .usdz)")
    view.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    view.add_argument("--camera", help="the render camera to highlight (prim path or name)")
    view.add_argument("--show", default="geometry,cameras,lights",
                      help="comma-separated: geometry, instances, cameras, lights, voxels, vpls, lgh "
                      "(default: %(default)s)")
    view.add_argument("--octree-resolution", type=int, default=64, metavar="N",
                      help="voxels: the sparse voxel octree's occupied voxels at N^3, a power of two from 8 up "
                      "(default: %(default)s)")
    view.add_argument("--voxel-resolution", action=_Renamed, new="--octree-resolution",
                      why="--voxel-resolution is usdml render's voxel arrays' resolution")
    view.add_argument("--lgh-level", type=int, default=1, metavar="L",
                      help="lgh: the grid lights of level L, 1 = S1 (default: %(default)s)")
    view.add_argument("--png", help="write the picture here (off-screen)")
    view.add_argument("--interactive", action="store_true", help="open a window instead (needs a display)")
    view.add_argument("--window-size", default="1280,720", metavar="W,H", help="pixels (default: %(default)s)")
    view.set_defaults(run=_cmd_view)

    compare = sub.add_parser("compare", help="one frame two ways: error of a method against its reference")
    _add_stage_args(compare, COMPARE)
    compare.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    compare.add_argument("--visibility", help="approximate visibility backend to compare against exact (voxel)")
    compare.add_argument("--against", help="reference method (default: exact for --visibility, vpl-bruteforce for --gi; all for --direct)")
    compare.add_argument("--heatmap", metavar="PNG", help="with --visibility: write the shadow error heat map "
                         "(paper 000 Fig. 6: blue darker, red brighter, error x 10)")
    compare.add_argument("--plot", metavar="PREFIX", help="with --visibility: write PREFIX.heatmap.png (the heat map) "
                         "and PREFIX.hist.png (histograms of the per-pixel errors)")
    compare.add_argument("--imageWidth", type=int, default=128, metavar="W", help="image width in pixels (default: %(default)s)")
    compare.add_argument("--reference-pixels", type=int, metavar="N",
                         help="with --direct lgh --against all: shade the every-light reference on N random pixels "
                              "only and extrapolate its time (for 100,000 lights and more)")
    add_cmdline_args(compare, COMPARE, "device")
    compare.add_argument("--png", metavar="PREFIX", help="write PREFIX_direct/indirect/color.png")
    compare.add_argument("--json", action="store_true", help="print JSON")
    add_cmdline_args(compare, COMPARE)
    compare.set_defaults(run=_cmd_compare)

    bench = sub.add_parser("bench", help="time the visibility queries of one frame")
    _add_stage_args(bench, BENCH)
    bench.add_argument("--visibility", action="append", help="backend to time (repeat for several; default exact)")
    bench.add_argument("--imageWidth", type=int, default=512, metavar="W", help="image width in pixels (default: %(default)s)")
    bench.add_argument("--frame", type=float, help="timecode (default: the stage's start)")
    add_cmdline_args(bench, BENCH, "device")
    bench.add_argument("--json", action="store_true", help="print JSON")
    add_cmdline_args(bench, BENCH)
    bench.set_defaults(run=_cmd_bench)

    bake = sub.add_parser("bake", help="build the voxel arrays (or the static SVO) of a stage into the cache")
    _add_stage_args(bake, BAKE)
    bake.add_argument("--backend", choices=_Bakers(), default="voxel",
                      help="whose structures to bake: voxel arrays (usdml:voxel settings) or the static sparse "
                           "voxel octree (usdml:svo settings) (default: %(default)s)")
    bake.add_argument("--frames", help="FrameSpec whose prototypes to bake (default: the start frame)")
    add_cmdline_args(bake, BAKE, "device")
    bake.add_argument("--cache", metavar="DIR", help="cache folder (default: $USDML_CACHE_DIR, else ~/.cache/usdml)")
    bake.add_argument("--json", action="store_true", help="print JSON")
    add_cmdline_args(bake, BAKE)
    bake.set_defaults(run=_cmd_bake)

    cache = sub.add_parser("cache", help="list or empty the on-disk cache of voxel arrays and octrees")
    cache.add_argument("action", nargs="?", choices=("list", "clean"), default="list",
                       help="list: entries, sizes, last use (the default); clean: remove entries (all of them unless "
                       "--older-than)")
    cache.add_argument("--older-than", type=float, metavar="DAYS", help="clean: only entries last used more than "
                       "DAYS days ago")
    cache.add_argument("--cache", metavar="DIR", help="cache folder (default: $USDML_CACHE_DIR, else ~/.cache/usdml)")
    cache.add_argument("--json", action="store_true", help="print JSON")
    cache.set_defaults(run=_cmd_cache)
    for command in sub.choices.values():
        _add_quiet_arg(command)
    return parser


def _unrecognized(parser: argparse.ArgumentParser, argv: list[str] | None, message: str) -> str:
    """argparse reports a subcommand's unknown flags as the top parser's: name the subcommand, its help
    and the flag each unknown one most resembles (``--direct-s``: did you mean --direct-shadow-samples?)."""
    prefix = f"{parser.prog}: unrecognized arguments: "
    argv = sys.argv[1:] if argv is None else list(argv)
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    command = next((a for a in argv if a in subs.choices), None)
    if not message.startswith(prefix) or command is None:
        return message
    import difflib

    sub = subs.choices[command]
    unknown = message[len(prefix):].split("; see ")[0]
    flags = [o for a in sub._actions if not isinstance(a, _Renamed) for o in a.option_strings if o.startswith("--")]
    hints = []
    for given in (u.split("=")[0] for u in unknown.split() if u.startswith("--")):
        longer = [f for f in flags if f.startswith(given)]       # an abbreviation: name the flags it starts
        if len(longer) > 3:
            longer = [f"one of the {len(longer)} flags starting {given}"]
        hints += longer or difflib.get_close_matches(given, flags, n=1, cutoff=0.75)
    return (f"{sub.prog}: unrecognized arguments: {unknown}"
            + (f"; did you mean {' or '.join(hints)}? (flags are never abbreviated)" if hints else "")
            + f"; see {sub.prog} --help")


class _OneLine(logging.Handler):
    """``usdml: warning: ...`` on whatever ``sys.stderr`` is when the record is emitted."""

    def emit(self, record: logging.LogRecord) -> None:
        print(f"usdml: {record.levelname.lower()}: {record.getMessage()}", file=sys.stderr)


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """A Python warning (pyvista's, Dask's, NumPy's ...) as one ``usdml: warning:`` line through the ``usdml``
    logger, so ``-q`` hides it with usdml's own: the package whose category it is (else the file and line
    that warned), the message's first line and the category."""
    text = next((part.strip() for part in str(message).splitlines() if part.strip()), "")
    package = category.__module__.partition(".")[0]
    where = package if package != "builtins" else f"{os.path.basename(filename)}:{lineno}"
    logging.getLogger("usdml").warning(f"{where}: {text} ({category.__name__})")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _ArgumentError as e:
        print(f"usdml: error: {_unrecognized(parser, argv, str(e))}", file=sys.stderr)
        return 2
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
        with warnings.catch_warnings():       # restored on return: main() may run inside a script or a test
            warnings.showwarning = _warning_line
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
