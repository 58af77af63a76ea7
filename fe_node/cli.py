"""Command line: ``python -m fe_node run|validate`` (see ``--help``)."""
from __future__ import annotations

import argparse
import json
import sys

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
    r = sub.add_parser("run", help="run a scenario open loop and print the melt pool")
    r.add_argument("--scenario", default="single-track", choices=NAMES, metavar="NAME",
                   help=f"one of: {', '.join(NAMES)} (default single-track)")
    r.add_argument("--power-w", type=float, help="constant laser power [W]")
    r.add_argument("--speed-mm-s", type=float, help="constant scan speed [mm/s]")
    r.add_argument("--h-um", type=float, help="fine element size [µm] (default 25)")
    r.add_argument("--jsonl", help="also write every observation to this JSON-lines file")
    r.add_argument("--json", action="store_true", help="print JSON only")
    v = sub.add_parser("validate", help="energy, Eagar-Tsai and mesh-convergence checks")
    v.add_argument("--h-um", type=float, default=25.0, help="fine element size [µm]")
    v.add_argument("--json", action="store_true", help="print JSON only")
    return p


def _run(args) -> dict:
    over = {}
    if args.power_w is not None:
        over["power_w"] = args.power_w
    if args.speed_mm_s is not None:
        if not args.speed_mm_s > 0:
            raise ValueError(f"speed must be > 0 mm/s, got {args.speed_mm_s}")
        over["speed_m_s"] = args.speed_mm_s * 1e-3
    if args.h_um is not None:
        over["h_fine_m"] = args.h_um * 1e-6
    sc = scenario(args.scenario, **over)
    obs = run_open_loop(sc, progress=True)
    if args.jsonl:
        import dataclasses
        with open(args.jsonl, "w") as f:
            for o in obs:
                f.write(json.dumps(dataclasses.asdict(o)) + "\n")
    res = dict(scenario=sc.name, **quasi_steady(obs))
    if sc.plan.total_length != sc.plan.lengths[0] or sc.profile.power_w.range()[0] != \
            sc.profile.power_w.range()[1] or sc.profile.speed_m_s.range()[0] != sc.profile.speed_m_s.range()[1]:
        res["summary"] = summary(obs)
    return res


def main(argv=None) -> int:
    """Entry point; returns the exit status (2 on bad parameters)."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "run":
            res = _run(args)
        else:
            from fe_node.validate import validate
            if not args.h_um > 0:
                raise ValueError(f"--h-um must be > 0, got {args.h_um}")
            res = validate(args.h_um * 1e-6, progress=True)
    except ValueError as e:
        print(f"fe_node: error: {e}", file=sys.stderr)
        return 2
    if not args.json:
        for k, val in res.items():
            print(f"{k:>28}: {val}")
    print(json.dumps(res))
    return 0
