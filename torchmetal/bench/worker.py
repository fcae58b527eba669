"""Child-process entry point: ``python -m torchmetal.bench.worker TASK CONFIG_JSON RESULT_PATH``
(one task) or ``python -m torchmetal.bench.worker --serve`` (jobs as JSON lines on stdin).

Runs one task of :mod:`torchmetal.bench.tasks` in a fresh interpreter (so peak-memory numbers
of different configurations never contaminate each other) and writes its JSON result. A stage
that cannot be imported yields ``{"not_available": reason}``; any other failure
``{"error": "Type: message"}`` — the runner reports both and carries on.
"""

from __future__ import annotations

import json
import math
import sys
import traceback

from torchmetal.bench.available import NotAvailable
from torchmetal.bench.tasks import TASKS


def _clean(x):
    """JSON-safe copy: non-finite floats become strings, tuples lists, numpy scalars floats."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "item") and not hasattr(x, "__len__"):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return repr(x)
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)


def _set_threads() -> None:
    import os

    n = os.environ.get("TORCHMETAL_BENCH_THREADS")
    if n:
        import torch

        torch.set_num_threads(int(n))


def run_task(task: str, cfg: dict) -> dict:
    """Run one task; failures become ``not_available`` / ``error`` entries instead of exceptions."""
    _set_threads()
    try:
        return TASKS[task](cfg)
    except NotAvailable as e:
        return {"not_available": str(e)}
    except Exception as e:  # reported, never fatal for the whole benchmark
        msg = str(e).splitlines()[0] if str(e) else ""
        return {"error": f"{type(e).__name__}: {msg}", "traceback": traceback.format_exc(limit=-4)}


MARKER = "@@TMBENCH "


def serve() -> int:
    """Read ``[task, config]`` JSON lines on stdin; answer each with one ``MARKER + JSON`` line.

    Quick runs keep one such process for every section: one interpreter start, not dozens.
    """
    import os

    out = os.fdopen(os.dup(1), "w")  # results go to a private copy of stdout …
    os.dup2(2, 1)  # … and anything a task prints goes to stderr, never into the protocol
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        task, cfg = json.loads(line)
        out.write(MARKER + json.dumps(_clean(run_task(task, cfg))) + "\n")
        out.flush()
    return 0


def main(argv: list[str]) -> int:
    """``TASK CONFIG_JSON RESULT`` runs one task; ``--serve`` answers jobs from stdin."""
    if argv and argv[0] == "--serve":
        return serve()
    task, cfg_json, result_path = argv
    result = run_task(task, json.loads(cfg_json))
    with open(result_path, "w") as f:
        json.dump(_clean(result), f)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
