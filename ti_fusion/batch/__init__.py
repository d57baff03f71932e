"""``ti-fusion batch MANIFEST``: many ``ti-fusion slam`` runs, each in its own process, scheduled on Ray.

- ``manifest``: the manifest read and every job checked before any starts (``read_manifest`` → ``Job``s);
- ``results``: the batch folder's job records, the results table (CSV, Markdown) and the ATE plot;
- ``runner``: the jobs on Ray (``run_batch``): resources per job, the progress line, stops without orphans.

The batch folder::

    BATCH/results.csv, results.md   one row per job (``results.COLUMNS``)
    BATCH/ate.png                   ATE per input per variant
    BATCH/runs/<job>/               the job's own ``ti-fusion slam`` run folder (summary.json, log.mcap, ...)
    BATCH/jobs/<job>.json, .log     what the batch knows of the job (arguments, exit, error), its output
"""
