"""Is ``algorithm.feedforward_handover`` safe as a default? Its check on the double lane change (held-out
seeds 100 and 101, none of them reported): each run is trained once with the library defaults (``lq_ss``
deployed) and its final policy evaluated on the course without and with the hand-over (the same trained
actor; training is unchanged by the setting). Reported per run: the evaluation of each, and the share of
the evaluation's policy calls outside the box of the training starts (:func:`training_box`).

Usage::

    PYTHONPATH=. python experiments/analysis/handover_dlc.py

writes ``experiments/results/handover_dlc/rows.json``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from mixedrl.algorithms.agpi import AGPI  # noqa: E402
from mixedrl.config import TrainConfig  # noqa: E402
from mixedrl.departures.anchor import HandoverPolicy, equilibrium_gain, training_box  # noqa: E402
from mixedrl.runs import atomic_write_text, eval_seeds, train  # noqa: E402
from mixedrl.tasks import task_from_config  # noqa: E402

OUT = ROOT / "experiments" / "results" / "handover_dlc"


class _Counted(torch.nn.Module):
    """``policy``, counting the observations it is called on that lie outside ``[low, high]``."""

    def __init__(self, policy: torch.nn.Module, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.policy, self.low, self.high, self.calls, self.outside = policy, low, high, 0, 0

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        o = obs.reshape(-1, obs.shape[-1])
        self.calls += o.shape[0]
        self.outside += int(((o > self.high) | (o < self.low)).any(-1).sum())
        return self.policy(obs)


def one(method: str, seed: int) -> dict[str, Any]:
    config = TrainConfig(method=method, seed=seed)
    task = task_from_config(config.task)
    trainer = AGPI(task, config)
    train(trainer, progress=False)
    plain = trainer.policy  # lq_ss, without the hand-over (the library default)
    low, high = training_box(task, config.seed)
    handover = HandoverPolicy(plain, low, high, equilibrium_gain(task, trainer._linearisation), plain.observation[0],
                              plain.action, plain.width, plain.bound)
    counted = _Counted(plain, low, high)
    seeds = eval_seeds(config)
    scalars = lambda d: {k: v for k, v in d.items() if isinstance(v, float)}  # noqa: E731
    without = scalars(task.evaluate(counted, seeds))
    with_ = scalars(task.evaluate(handover, seeds))
    return {"method": method, "seed": seed, "feedforward": trainer.feedforward, "without": without,
            "with_handover": with_, "outside_fraction": counted.outside / counted.calls,
            "box_low": low.tolist(), "box_high": high.tolist(), "config": config.to_dict()}


def main() -> None:
    torch.set_num_threads(1)
    rows = []
    for seed in (100, 101):
        for method in ("mixed", "model", "oracle"):
            r = one(method, seed)
            print(f"{method} {seed}: cost {r['without']['cost']:.3f} -> {r['with_handover']['cost']:.3f}, lateral "
                  f"{r['without']['lateral_mae']:.4f} -> {r['with_handover']['lateral_mae']:.4f}, outside the box "
                  f"{r['outside_fraction']:.1%}", flush=True)
            rows.append(r)
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "rows.json", json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
