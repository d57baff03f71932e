"""``ti-fusion batch MANIFEST``: every job of a manifest as its own ``ti-fusion slam`` run, on Ray, with one
results table (docs/BATCH.md)."""

from __future__ import annotations

HELP = "many slam runs from a manifest (inputs × variants) on Ray: one results table, resumable (pip install 'ti-fusion[batch]')"
USES_DATASET = False
USES_TAICHI = False   # each job starts its own; the batch itself never does
RESUMES_OUT = True    # --out holding an earlier batch of the same command is resumed, not refused


def add_arguments(parser) -> None:
    parser.add_argument("manifest", metavar="MANIFEST",
                        help="the jobs: a TOML, YAML or JSON file of inputs, each with its options, and optional "
                             "variants crossed with them (docs/BATCH.md)")
    parser.add_argument("--address", default=None, metavar="ADDRESS",
                        help="an existing Ray cluster (auto, HOST:PORT, ray://HOST:10001) instead of a local Ray "
                             "on this machine; the batch folder and inputs must be at the same paths on its nodes")
    parser.add_argument("--threads", type=int, default=1, metavar="N",
                        help="the CPUs each job asks Ray for, where the manifest does not say (threads = N): local "
                             "Ray runs cores / N jobs at once, each with up to 2N Taichi threads so that the last "
                             "job alone uses the idle CPUs (at most the cores; on --address: N) (default: 1)")
    parser.add_argument("--taichi-threads", type=int, default=None, metavar="N",
                        help="every job's Taichi CPU threads, whatever it asks Ray for (default: twice its "
                             "threads, at most the cores; on --address: its threads)")
    parser.add_argument("--jobs", type=int, default=None, metavar="N",
                        help="at most N jobs at once (default: as many as the CPUs allow)")
    parser.add_argument("--rerun-failed", action="store_true",
                        help="resuming: run the jobs that failed again too (finished ones are always skipped)")


def run(ctx) -> dict:
    from ti_fusion.batch.manifest import read_manifest
    from ti_fusion.batch.runner import Batch
    from ti_fusion.batch.results import DONE, FAILED
    from ti_fusion.errors import InputError

    args = ctx.args
    for name in ("threads", "jobs", "taichi_threads"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise InputError(None, f"--{name.replace('_', '-')} {value}: must be at least 1")
    manifest = read_manifest(args.manifest, default_threads=args.threads)
    say = (lambda line: None) if ctx.quiet else ctx.log
    batch = Batch(manifest, ctx.out.path, address=args.address, max_jobs=args.jobs,
                  rerun_failed=args.rerun_failed, progress=not ctx.quiet, say=say, taichi=args.taichi_threads)
    table = batch.run()
    if batch.ray_start_s is not None:
        # the interpreter's exit with Ray's modules loaded spends its time in the garbage collector's last
        # passes, which skip frozen objects (measured after a batch: 0.7 s -> 0.07 s at load 14)
        import gc

        gc.freeze()
    done = [r for r in table if r["status"] == DONE]
    failed = [r for r in table if r["status"] == FAILED]
    line = f"{len(table)} jobs: {len(done)} done, {len(failed)} failed"
    if len(done) + len(failed) < len(table):
        line += f", {len(table) - len(done) - len(failed)} not run"
    ctx.log(line + f"; results: {ctx.out.path}/results.md" +
            (f" (failed: {', '.join(r['job'] for r in failed[:3])}{', ...' if len(failed) > 3 else ''})" if failed else ""))
    return {"frames": sum(r["frames"] or 0 for r in done), "jobs": len(table), "done": len(done),
            "failed": len(failed), "ran": batch.counts["ran"], "skipped": batch.counts["skipped_done"],
            "ray_start_s": batch.ray_start_s, "timeline": batch.timeline(),
            "started_at": batch.origin,
            "manifest": str(manifest.path.resolve()), "results": "results.csv",
            "exit_code": 1 if failed else 0}
