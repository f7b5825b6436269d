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


def _cmd_info(args: argparse.Namespace) -> int:
    from usdml.info import format_info, stage_info
    from usdml.stage import StageDelegate

    started = time.perf_counter()
    delegate = StageDelegate(args.stage, camera=args.camera, render_settings_path=args.render_settings)
    info = stage_info(delegate, args.time, started=started)
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(format_info(info))
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
    return parser


class _OneLine(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return f"usdml: {record.levelname.lower()}: {record.getMessage()}"


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
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLine())
    log = logging.getLogger("usdml")
    log.handlers[:] = [handler]
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
