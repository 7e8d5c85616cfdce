"""``hdrqn export``: a trained policy as ONNX models plus ``policy.json``, for acting
without torch (:mod:`hdrqn_ros.deploy`, docs/deploy.md)."""
from __future__ import annotations

import sys

from hdrqn_ros.cli.common import given_paths


def add_export(sub) -> None:
    parser = sub.add_parser("export", help="write a checkpoint's controllers as ONNX models (torch-free acting)",
                            description="Writes the meta- and sub-controller of a checkpoint as ONNX models (LSTM "
                                        "state as explicit inputs and outputs) and policy.json into OUT; the "
                                        "controller nodes act on it with onnxruntime and numpy only (docs/deploy.md).")
    parser.add_argument("--checkpoint", required=True, metavar="PATH", help="e.g. RUN_DIR/checkpoints/last.pt")
    parser.add_argument("--out", required=True, metavar="DIR", help="the policy directory to write")
    parser.add_argument("--no-verify", action="store_true",
                        help="skip comparing ONNX Runtime with torch on random inputs after the export")


def cmd_export(args) -> int:
    from hdrqn_ros.extras import require

    given_paths(checkpoint=args.checkpoint, out=args.out)
    require("deploy", "hdrqn export", ("onnx",) if args.no_verify else None)
    from hdrqn_ros.training.export import export_policy

    out = export_policy(args.checkpoint, args.out, verify=not args.no_verify)
    print(f"hdrqn export: {args.checkpoint} -> {out} (policy.json and the ONNX models)", file=sys.stderr)
    return 0
