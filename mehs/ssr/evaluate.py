"""SSR evaluation, one import for the three concerns it is split into.

- :mod:`mehs.ssr.protocol` — which settings each model is scored under;
- :mod:`mehs.ssr.scoring` — :func:`evaluate`, :func:`summarise`;
- :mod:`mehs.ssr.timing` — :func:`time_models` (Table 5);
- :mod:`mehs.ssr.results_io` — tables and the results folder (format ``mehs-evaluation/1``).
"""

from __future__ import annotations

from mehs.ssr.protocol import PREPROCESS_CHOICES, allowed, model_settings  # noqa: F401
from mehs.ssr.results_io import (EVALUATION_FORMAT, format_tables, is_evaluation_folder,  # noqa: F401
                                 load_results, per_scene_blocks, spread_block, table_blocks,
                                 write_results)
from mehs.ssr.scoring import (EvaluationResult, config_key, evaluate, parse_key,  # noqa: F401
                              parse_pixels, summarise)
from mehs.ssr.timing import PAPER_SECONDS, time_models  # noqa: F401

__all__ = ["EVALUATION_FORMAT", "EvaluationResult", "PAPER_SECONDS", "PREPROCESS_CHOICES",
           "allowed", "config_key", "evaluate", "format_tables", "is_evaluation_folder",
           "load_results", "model_settings", "parse_key", "parse_pixels", "per_scene_blocks",
           "spread_block", "summarise", "table_blocks", "time_models", "write_results"]
