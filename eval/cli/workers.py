"""The `--jobs N` and `--ray [ADDRESS]` flags of the campaign commands (boundary, paper,
faults): where the scenarios run (eval.experiments.campaign.Workers). Results do not
depend on them."""
from __future__ import annotations

from eval.cli.args import integer
from eval.cli.io import UsageError
from eval.cli.progress import phase
from eval.experiments.campaign import LOCAL_RAY, Workers, WorkersError, connect_ray, default_jobs

JOBS = integer(1, 1024)


def add_worker_flags(parser, ray: bool = True) -> None:
    """Add --jobs (default: every core) and, with `ray`, --ray to `parser`."""
    parser.add_argument("--jobs", type=JOBS, default=default_jobs(),
                        help=f"worker processes, {JOBS.range}; default: this machine's cores")
    if ray:
        parser.add_argument("--ray", nargs="?", const=LOCAL_RAY, default=None, metavar="ADDRESS",
                            help="run the scenarios on Ray: a local instance with --jobs CPUs, or the cluster at "
                                 "ADDRESS (host:port of its head; its nodes need vitreoguard installed)")


def workers_of(args) -> Workers:
    """The Workers of the parsed flags, Ray joined (or started) already: call it before
    anything is written. UsageError (exit 2) when Ray cannot be had."""
    workers = Workers(jobs=args.jobs, ray=getattr(args, "ray", None))
    if workers.ray is not None:
        try:
            with phase(f"starting / joining Ray ({workers.describe()})"):
                connect_ray(workers)
        except WorkersError as exc:
            raise UsageError(str(exc)) from None
    return workers
