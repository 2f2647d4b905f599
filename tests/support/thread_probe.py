"""A pipeline for the worker's thread tests: records the thread state of the process that runs the job into
``threads.json`` of the run folder, then does what the scripted pipeline does (``scripted_pipeline``).

Select it with ``PANOGS_TEST_PIPELINE=thread_probe`` and ``tests/support`` on the Python path (pipeline_stand_in.py).
A test double, not shipped.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import cv2
import scripted_pipeline as scripted
import threadpoolctl
import torch

from panogs_core.threads import THREAD_COUNT_VARIABLES, WAIT_POLICY

STAGES = scripted.STAGES
make_config = scripted.make_config


def thread_state() -> dict[str, Any]:
    """This process's pools as the libraries report them, and the variables they were started from."""
    pools: dict[str, int] = {}
    for pool in threadpoolctl.threadpool_info():
        pools[pool["internal_api"]] = int(pool["num_threads"])  # openblas, openmp, mkl
    names = (*THREAD_COUNT_VARIABLES, *WAIT_POLICY, "OPENBLAS_CORETYPE")
    return {
        "pid": os.getpid(),
        "ppid": os.getppid(),
        "torch_threads": torch.get_num_threads(),
        "opencv_threads": cv2.getNumThreads(),
        "pools": pools,
        "environ": {name: os.environ.get(name) for name in names},
    }


def run_pipeline(bundle: str | Path, out_dir: str | Path, config: dict[str, Any] | None = None, **kw: Any) -> Any:
    """Record the thread state, then run the scripted stages."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / "threads.json").write_text(json.dumps(thread_state()))
    return scripted.run_pipeline(bundle, out_dir, config, **kw)
