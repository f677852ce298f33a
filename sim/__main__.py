"""Command line of the beam physics: ``python -m sim modes|simulate``.

Examples
--------
python -m sim modes --json
python -m sim modes --config results/s1/config.yaml --json --n-modes 3 --tune-to-hz 4.8
python -m sim modes --config results/s1/config.yaml --json --out results/s1/sim/modes.json
python -m sim simulate --config results/s1/config.yaml --out-dir results/s1/sim
python -m sim render ...   (forwarded to sim.render_cli, the renderer's command line)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from refflow.config import load_config
from sim.beam import SimConfig, modal_analysis, simulate, tune_to_hz


def _modes(args: argparse.Namespace) -> int:
    raw = load_config(args.config) if args.config else {}
    cfg = SimConfig.from_dict(raw)
    result = modal_analysis(cfg, n_modes=args.n_modes)
    if args.tune_to_hz is not None:
        tuned, change = tune_to_hz(cfg, args.tune_to_hz, parameter=args.tune_parameter)
        tuned_result = modal_analysis(tuned, n_modes=args.n_modes)
        result = {**tuned_result, "untuned": {k: result[k] for k in (
            "model_hz", "model_hz_no_gravity", "euler_bernoulli_hz")}, "tuning": change,
            "tuned_beam": dataclasses.asdict(tuned.beam)}
    if args.out:
        from refflow.io import write_json
        write_json(args.out, result)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{'mode':>4} {'model_hz':>10} {'no_grav_hz':>10} {'euler_b_hz':>10}")
        for k, (f, f0, fe) in enumerate(zip(result["model_hz"], result["model_hz_no_gravity"],
                                            result["euler_bernoulli_hz"], strict=True)):
            print(f"{k + 1:>4} {f:10.4f} {f0:10.4f} {fe:10.4f}")
        if "tuning" in result:
            print("tuning:", json.dumps(result["tuning"]))
    return 0


def _simulate(args: argparse.Namespace) -> int:
    raw = load_config(args.config) if args.config else {}
    sidecar = simulate(raw, args.out_dir, progress=not args.quiet)
    speed = sidecar["timings"]["simulated_s_per_wall_s"]
    print(f"wrote {args.out_dir}/sensor.csv, shapes.npz, sim.json "
          f"({speed:.1f} simulated s per wall s, engine {sidecar['model']['engine']})",
          file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "render":
        # Rendering lives in sim.render_cli (another owner); import it only when asked
        # so the physics commands do not need the rendering stack.
        from sim.render_cli import main as render_main
        return render_main(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m sim", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    modes = sub.add_parser("modes", help="modal analysis of the MuJoCo beam")
    modes.add_argument("--config", help="scenario config (YAML or JSON)")
    modes.add_argument("--json", action="store_true", help="print JSON")
    modes.add_argument("--out", help="also write the JSON to this file (atomically)")
    modes.add_argument("--n-modes", type=int, default=3)
    modes.add_argument("--tune-to-hz", type=float, default=None,
                       help="fit an effective parameter so mode 1 has this frequency")
    modes.add_argument("--tune-parameter", default="youngs_modulus_gpa",
                       choices=["youngs_modulus_gpa", "tip_mass_kg"])
    modes.set_defaults(func=_modes)
    simulate_p = sub.add_parser("simulate", help="simulate and write sensor.csv, shapes.npz, sim.json")
    simulate_p.add_argument("--config", required=True, help="scenario config (YAML or JSON)")
    simulate_p.add_argument("--out-dir", required=True)
    simulate_p.add_argument("--quiet", action="store_true", help="no progress bar")
    simulate_p.set_defaults(func=_simulate)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
