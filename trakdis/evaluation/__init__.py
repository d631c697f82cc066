"""Evaluation: playing episodes of a policy in a batched env and summarising their scores
(:mod:`.episodes`), the scripted expert's scores cached on disk (:mod:`.expert_scores`), and
evaluations of a saved policy in a background process at low priority (:mod:`.background`), a
run's evaluation protocol: the same episodes every time, their scores logged (:mod:`.protocol`), an
evaluation cut into parts that run side by side and joined again (:mod:`.chunks`), and
where a cloth policy closes its grippers (:mod:`.grasps`)."""
from .background import BackgroundEvaluation
from .episodes import (
    COLLECTORS,
    CollectorName,
    EpisodeResults,
    EpisodeStream,
    episode_frames,
    episode_score,
    markdown_table,
    paired_difference,
    pick_candidate,
    race_survivors,
    read_final_scores,
    run_episodes,
    split_episodes,
    standard_error,
    summarize,
    worker_env_fns,
    write_summary_table,
)
from .chunks import evaluation_parts, merge_evaluations
from .grasps import FAR_CLOSE_CM, grasp_report, summarize_grasps
from .protocol import EvalConfig, EvalProtocol, RunEnvs, compare_scores, log_scores
from .expert_scores import (
    ExpertScoreError,
    expert_score_key,
    expert_score_path,
    read_expert_scores,
    write_expert_scores,
)

__all__ = [
    "COLLECTORS",
    "CollectorName",
    "evaluation_parts",
    "merge_evaluations",
    "worker_env_fns",
    "BackgroundEvaluation",
    "EvalConfig",
    "EvalProtocol",
    "RunEnvs",
    "compare_scores",
    "log_scores",
    "EpisodeResults",
    "EpisodeStream",
    "episode_frames",
    "episode_score",
    "markdown_table",
    "paired_difference",
    "pick_candidate",
    "race_survivors",
    "read_final_scores",
    "run_episodes",
    "split_episodes",
    "standard_error",
    "summarize",
    "write_summary_table",
    "ExpertScoreError",
    "expert_score_key",
    "expert_score_path",
    "read_expert_scores",
    "write_expert_scores",
    "FAR_CLOSE_CM",
    "grasp_report",
    "summarize_grasps",
]
