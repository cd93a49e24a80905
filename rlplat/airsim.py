"""``python -m rlplat.airsim <verb> [...]``: the AirSim tools.

Verbs:
    settings out=PATH [port=P] [overrides]   write settings.json for the team of the train config
                                    (e.g. ``scenario=pursuit_2v1 dynamics=airsim``)
    serve [--settings FILE] [--port P] [--clock-speed K] [--realtime] [overrides]
                                    serve the loopback AirSim-protocol test server (for FILE,
                                    else for the configured team) until Ctrl-C
    calibrate [dynamics.endpoints=[HOST:PORT]] [out=FILE] [options] [overrides]
                                    fly velocity step responses on the simulator and fit the
                                    velocity dynamics to them (default out:
                                    conf/dynamics/velocity_calibrated.yaml)
    replay recording=FILE [out=CSV] [dynamics overrides]
                                    replay a recorded episode's commands through the embedded
                                    dynamics; per-step position error
    sim2sim run_dir=DIR dynamics.endpoints=[HOST:PORT,...] [split=test] [reference=NAME]
            [reference_tick=S]      the run's policy on its embedded dynamics (stepped in
                                    whole physics ticks of S s, as AirSim steps: 0.003) and
                                    on the simulator, compared per scenario
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence

from rlplat.cli import exit_on_error

VERBS = ("settings", "serve", "calibrate", "replay", "sim2sim")


HELP = {"-h", "--help"}


def usage(verb: str) -> str:
    """The module docstring's lines on ``verb`` (its line under Verbs, then the deeper ones)."""
    lines = __doc__.splitlines()

    def heads(line: str) -> bool:  # a verb's own line: indented by four, no more
        return line.startswith("    ") and not line.startswith("     ")

    start = next(i for i, line in enumerate(lines) if heads(line) and line.split()[0] == verb)
    end = next((i for i in range(start + 1, len(lines)) if heads(lines[i])), len(lines))
    text = "\n".join(line.strip() for line in lines[start:end] if line.strip())
    return f"python -m rlplat.airsim {text}"


@exit_on_error
def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] in HELP:
        print(__doc__.strip())
        return 0
    if len(args) > 1 and args[0] in VERBS and args[0] != "serve" and HELP & set(args[1:]):
        print(usage(args[0]))  # serve's own --help is argparse's
        return 0
    if not args or args[0] not in VERBS:
        given = repr(args[0]) if args else "none"
        print(
            f"usage: python -m rlplat.airsim {{{','.join(VERBS)}}} ...; got {given}",
            file=sys.stderr,
        )
        return 2
    from rlplat.experiment import airsim_tools

    verb, rest = args[0], args[1:]
    if verb == "serve":
        return airsim_tools.serve_command(rest)
    if verb == "settings":
        print(airsim_tools.settings_command(rest))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    print(getattr(airsim_tools, f"{verb}_command")(rest))
    return 0


if __name__ == "__main__":
    sys.exit(main())
