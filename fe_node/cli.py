"""Command line: ``python -m fe_node run|validate|calibrate`` (see ``--help``)."""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from fe_node.driver import quasi_steady, run_open_loop, summary
from fe_node.scenarios import NAMES, scenario


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        print(f"fe_node: error: {message}", file=sys.stderr)
        sys.exit(2)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m fe_node", description="meltloop FE plant (scikit-fem). "
                "Without a subcommand (or with 'node') the zenoh node starts: "
                "python -m fe_node node --help.")
    sub = p.add_subparsers(dest="command", parser_class=_Parser)
    config_help = "TOML file whose [plant] table sets the plant (the same table as launch.py --config)"
    r = sub.add_parser("run", help="run a scenario open loop and print the melt pool")
    r.add_argument("--scenario", default="single-track", choices=NAMES, metavar="NAME",
                   help=f"one of: {', '.join(NAMES)} (default single-track)")
    r.add_argument("--power-w", type=float, help="constant laser power [W]")
    r.add_argument("--speed-mm-s", type=float, help="constant scan speed [mm/s]")
    r.add_argument("--h-um", type=float, help="fine element size [µm] (default 25)")
    r.add_argument("--config", type=Path, help=config_help)
    r.add_argument("--jsonl", help="also write every observation to this JSON-lines file")
    r.add_argument("--json", action="store_true", help="print JSON only")
    v = sub.add_parser("validate", help="check the plant against analytic, numerical and measured references "
                       "(exit 1 naming each failed check)")
    v.add_argument("--h-um", type=float, help="fine element size [µm] (default 25)")
    v.add_argument("--config", type=Path, help=config_help)
    v.add_argument("--json", action="store_true", help="print JSON only")
    c = sub.add_parser("calibrate", help="fit absorptivity, keyhole radius and liquid conductivity factors "
                       "to the AM-Bench tracks")
    c.add_argument("--config", type=Path, help=config_help + " over the physical preset; its values start the fit")
    c.add_argument("--max-evaluations", type=int, default=40, help="plant evaluations of the fit (default 40)")
    c.add_argument("--out", type=Path, help="write the calibration record here (default: print only); "
                   "fe_node/calibration.json is the record the plant's defaults come from")
    c.add_argument("--json", action="store_true", help="print JSON only")
    return p


def plant_table(path: Path | None) -> dict:
    """The ``[plant]`` table of a TOML file (``{}`` without one); ValueError naming what is wrong."""
    from messages.cli import UsageError
    from messages.config import load_toml

    try:
        data = load_toml(path)
    except UsageError as err:
        raise ValueError(str(err)) from None
    unknown = set(data) - {"plant", "controller"}
    if unknown:
        raise ValueError(f"{path}: unknown table(s) {', '.join(sorted(unknown))}; expected [plant], [controller]")
    return dict(data.get("plant", {}))


def _settings(args, preset: str | None = None):
    """The plant settings of ``--config`` and ``--h-um`` (ValueError naming a bad key); ``preset``
    applies under the table (:mod:`fe_node.presets`)."""
    over = plant_table(args.config)
    if preset is not None:
        over = {"preset": preset, **over}
    h_um = getattr(args, "h_um", None)     # calibrate has no --h-um: the calibration's mesh is the plant's
    if h_um is not None:
        if not h_um > 0:
            raise ValueError(f"--h-um must be > 0, got {h_um}")
        over["h_fine_m"] = h_um * 1e-6
    try:
        return scenario("single-track", **over).settings
    except ValueError as err:
        raise ValueError(f"{args.config} [plant]: {err}" if args.config else str(err)) from None


def _run(args) -> dict:
    over = plant_table(args.config)
    if args.power_w is not None:
        over["power_w"] = args.power_w
    if args.speed_mm_s is not None:
        if not args.speed_mm_s > 0:
            raise ValueError(f"speed must be > 0 mm/s, got {args.speed_mm_s}")
        over["speed_m_s"] = args.speed_mm_s * 1e-3
    if args.h_um is not None:
        over["h_fine_m"] = args.h_um * 1e-6
    try:
        sc = scenario(args.scenario, **over)
    except ValueError as err:
        raise ValueError(f"{args.config} [plant]: {err}" if args.config else str(err)) from None
    obs = run_open_loop(sc, progress=not args.json)
    if args.jsonl:
        with open(args.jsonl, "w") as f:
            for o in obs:
                f.write(json.dumps(dataclasses.asdict(o)) + "\n")
    res = dict(scenario=sc.name, **quasi_steady(obs))
    if sc.plan.total_length != sc.plan.lengths[0] or sc.profile.power_w.range()[0] != \
            sc.profile.power_w.range()[1] or sc.profile.speed_m_s.range()[0] != sc.profile.speed_m_s.range()[1]:
        res["summary"] = summary(obs)
    return res


def main(argv=None) -> int:
    """Entry point; returns the exit status (2 on bad parameters, 1 when ``validate`` fails a check)."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "run":
            res = _run(args)
        elif args.command == "validate":
            from fe_node.validate import validate
            res = validate(_settings(args), progress=not args.json)
        else:
            from fe_node.calibrate import calibrate
            if args.max_evaluations < 1:
                raise ValueError(f"--max-evaluations must be >= 1, got {args.max_evaluations}")
            res = calibrate(_settings(args, preset="physical"), args.max_evaluations,
                            log=(lambda m: None) if args.json else (lambda m: print(m, file=sys.stderr)))
            res["command"] = " ".join(["python -m fe_node", *(sys.argv[1:] if argv is None else argv)])
            if args.out:
                args.out.write_text(json.dumps(res, indent=1) + "\n")
    except ValueError as e:
        print(f"fe_node: error: {e}", file=sys.stderr)
        return 2
    if not args.json:
        for k, val in res.items():
            if k not in ("details", "cases"):
                print(f"{k:>28}: {val}")
    print(json.dumps(res))
    if args.command == "validate" and not res["passed"]:
        print("fe_node validate: FAILED: " + "; ".join(res["failed"]), file=sys.stderr)
        return 1
    return 0
