"""The method's network in torch (offline only: training, checkpoint conversion, parity tests).

Layer layout and state-dict keys match the authors' released checkpoints exactly
(``../shared/reference/README.md``), so ``load_reference_member`` loads them unchanged.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn


class SlipNet(nn.Module):
    """Encoder MLP -> GRU cell -> predictor MLP -> 2-class softmax. ``forward(x, h) -> (probs, h_next)``."""

    def __init__(self, input_size: int = 640, hidden: int = 128, enc: int = 1024, pred: tuple[int, int] = (256, 128),
                 aux: int = 0):
        super().__init__()
        self.input_size = input_size
        self.hidden = hidden
        self.projector = nn.Sequential(
            nn.Linear(input_size, enc), nn.BatchNorm1d(enc), nn.ReLU(),
            nn.Linear(enc, hidden), nn.BatchNorm1d(hidden), nn.ReLU(),
        )
        self.rnn = nn.GRUCell(hidden, hidden)
        self.predictor = nn.Sequential(
            nn.Linear(hidden, pred[0]), nn.BatchNorm1d(pred[0]), nn.ReLU(),
            nn.Linear(pred[0], pred[1]), nn.BatchNorm1d(pred[1]), nn.ReLU(),
            nn.Linear(pred[1], 2), nn.BatchNorm1d(2), nn.Softmax(dim=1),
        )
        # Auxiliary per-pillar head (training only, ``aux`` > 0): one slip logit per input pillar read from the
        # GRU state, supervised by the simulator's per-pillar slip truth. It asks the state to carry *which
        # pillars slide*, the physical content of incipient slip, rather than a clock of when our scripts move.
        self.aux = aux
        self.aux_head = nn.Linear(hidden, aux) if aux > 0 else None

    def logits(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-softmax outputs (after the last BatchNorm) and the next hidden state."""
        h = self.rnn(self.projector(x), h)
        return self.predictor[:-1](h), h

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z, h = self.logits(x, h)
        return torch.softmax(z, dim=1), h

    def config(self) -> dict:
        """Constructor arguments, stored in checkpoints."""
        return {
            "input_size": self.input_size,
            "hidden": self.hidden,
            "enc": self.projector[0].out_features,
            "pred": (self.predictor[0].out_features, self.predictor[3].out_features),
            "aux": self.aux,
        }


def load_reference_member(path: str | Path) -> SlipNet:
    """One of the authors' ``ckpt_final_model_K.pth`` files as an eval-mode SlipNet (640 inputs, hidden 128)."""
    state = torch.load(Path(path), map_location="cpu", weights_only=True)
    net = SlipNet(input_size=state["projector.0.weight"].shape[1], hidden=state["rnn.weight_hh"].shape[1])
    net.load_state_dict(state)
    return net.eval()


def load_reference_ensemble(folder: str | Path) -> list[SlipNet]:
    """All ``ckpt_final_model_*.pth`` in ``folder``, sorted by member index."""
    paths = sorted(Path(folder).glob("ckpt_final_model_*.pth"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    if not paths:
        raise FileNotFoundError(f"{folder}: no ckpt_final_model_*.pth")
    return [load_reference_member(p) for p in paths]


@torch.no_grad()
def run_sequence(members: list[SlipNet], windows: torch.Tensor) -> torch.Tensor:
    """Reference way of running: members in a loop, one window at a time. [K, D] -> [Z, K] P(slip)."""
    out = torch.zeros(len(members), len(windows))
    for z, net in enumerate(members):
        h = torch.zeros(1, net.hidden)
        for k in range(len(windows)):
            p, h = net(windows[k : k + 1], h)
            out[z, k] = p[0, 1]
    return out
