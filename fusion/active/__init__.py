"""Active touch: next-touch policies planned on the camera's view, sequential decisions, a Gymnasium environment.

- :mod:`fusion.active.policies`: ``random``, ``saliency`` and ``information`` (contours simulated on the smoothed
  visual model; the one whose outcome best serves the camera's belief, :func:`plan_scores`), with the contract
  that a policy never reads the true object.
- :mod:`fusion.active.episode`: :func:`run_episode`, touches fused by the log rule until a confidence threshold
  or a touch budget.
- :mod:`fusion.active.replay`: a candidate bank per object (simulated and real readings of the information policy's
  candidates), over which next-touch criteria replay an episode's decisions offline.
- :mod:`fusion.active.figure`: one episode as a figure (``make demo``).
- :mod:`fusion.active.env`: ``ActiveTouchEnv``, the same loop as a Gymnasium / ``ap_gym`` active-classification
  environment (imported on demand: it needs ``gymnasium`` and ``ap_gym``).
"""

from fusion.active.episode import Episode, run_episode, stopped, touch_seed
from fusion.active.policies import (
    POLICIES,
    ActiveState,
    InformationPolicy,
    Policy,
    RandomPolicy,
    SaliencyPolicy,
    information_gain,
    make_policy,
    noisy_copy,
    plan_scores,
    same_plane,
    smoothed,
    visual_belief,
    visual_key,
)

__all__ = ["POLICIES", "ActiveState", "Episode", "InformationPolicy", "Policy", "RandomPolicy", "SaliencyPolicy",
           "information_gain", "make_policy", "noisy_copy", "plan_scores", "run_episode", "same_plane", "smoothed",
           "stopped", "touch_seed", "visual_belief", "visual_key"]
