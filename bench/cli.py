"""`palletpilot bench NAME [--json] [options]`: run one benchmark and print its figures."""

from __future__ import annotations

import argparse
import importlib
import json
import sys

from palletpilot.bench import BENCHMARKS
from palletpilot.executor.apps.cli_args import Parser
from palletpilot.executor.apps.cli_outcome import EXIT_BAD_INPUT, EXIT_OK


def cmd_bench(args: argparse.Namespace, extra: list[str]) -> int:
    """Run one benchmark by name (options after NAME go to the benchmark) and print its figures."""
    if args.name not in BENCHMARKS:
        print(f"bench: unknown benchmark '{args.name}' (known: {', '.join(sorted(BENCHMARKS))})", file=sys.stderr)
        return EXIT_BAD_INPUT
    module = importlib.import_module(BENCHMARKS[args.name])
    parser = Parser(prog=f"palletpilot bench {args.name}")
    module.add_arguments(parser)
    result = module.run(parser.parse_args(extra))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        width = max(len(k) for k in result)
        for key, value in result.items():
            print(f"{key:<{width}}  {value}")
    return EXIT_OK


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add `bench` to the `palletpilot` sub-commands; it takes the options it does not know itself."""
    bench = sub.add_parser("bench", help="run a benchmark (options after NAME go to the benchmark)")
    bench.add_argument("name", help=", ".join(sorted(BENCHMARKS)))
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(func=cmd_bench, takes_extra=True)
