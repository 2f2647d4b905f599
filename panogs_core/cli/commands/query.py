"""``panogs query``: the instances of a finished run that match a text or a query vector, best first."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np


def add_command(sub: Any) -> None:
    """Add ``query`` to an argparse subparsers object."""
    p = sub.add_parser("query", help="find instances by text or vector")
    p.add_argument("run", help="the --out folder of a run")
    p.add_argument("text", nargs="*", help="a class name or free text")
    p.add_argument("--vector", help=".npy file with one (D,) query embedding")
    p.add_argument("--top-k", type=int, default=10)
    p.add_argument("--min-score", type=float, default=0.5)
    p.add_argument("--model-path", help="text encoder folder or hub name (needed for free text in CLIP space)")
    p.set_defaults(func=run_query)


def run_query(args: argparse.Namespace) -> int:
    """Score the run's instances against the query and print the hits with their boxes, or, when none passes
    ``--min-score``, the closest candidates with their scores."""
    import numpy as np

    from panogs_core.io.run_folder import load_result
    from panogs_core.language.query import format_answer, rank_instances
    from panogs_core.language.text_encoders import get_text_encoder

    loaded = load_result(args.run)
    query: str | np.ndarray = np.load(args.vector) if args.vector else " ".join(args.text)
    encoder = None
    if args.model_path and isinstance(query, str):
        encoder = get_text_encoder(loaded.feature_space, model_path=args.model_path)
    answer = rank_instances(
        loaded.instances,
        loaded.vocabulary,
        query,
        feature_space=loaded.feature_space,
        encoder=encoder,
        top_k=args.top_k,
        min_score=args.min_score,
    )
    print(format_answer(args.vector or repr(query), answer))
    return 0
