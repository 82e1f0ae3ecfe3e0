"""The method's network in torch (offline only: training, checkpoint conversion, parity tests).

Layer layout and state-dict keys match the authors' released checkpoints exactly
(``../shared/reference/README.md``), so ``load_reference_member`` loads them unchanged.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F


class PillarTiedLinear(nn.Module):
    """The encoder's first layer with one set of weights for every pillar.

    A window is [T, P, C] flattened time-major. Each pillar p gets ``units`` outputs from its own window
    (weights ``own``, the same for every pillar) and from the mean window of all pillars (``context``):
    ``y[p] = own . x[p] + context . mean_q x[q] + bias``. So every pillar is read by the same rule, relative
    to the rest of the grasp, whichever pillars an object happens to load: what the reference-pillar and
    deceleration rules do by construction, and what a dense layer must learn pillar by pillar from the few
    contact layouts a data set holds. The map is linear in the window, so ``dense_weight`` writes it as the
    dense layer of ``SlipNet``'s layout and the exported graph and the daemon do not change.
    """

    def __init__(self, window: int, pillars: int, channels: int, units: int) -> None:
        super().__init__()
        self.window, self.pillars, self.channels, self.units = window, pillars, channels, units
        fan_in = window * channels
        self.own = nn.Parameter(torch.empty(units, window, channels))
        self.context = nn.Parameter(torch.empty(units, window, channels))
        self.bias = nn.Parameter(torch.zeros(units))
        bound = 1.0 / fan_in**0.5
        nn.init.uniform_(self.own, -bound, bound)
        nn.init.uniform_(self.context, -bound, bound)

    @property
    def out_features(self) -> int:
        return self.pillars * self.units

    def dense_weight(self) -> torch.Tensor:
        """[P * units, T * P * C]: output (p, j), input (t, q, c)."""
        eye = torch.eye(self.pillars, dtype=self.own.dtype, device=self.own.device)
        own = torch.einsum("pq,jtc->pjtqc", eye, self.own)
        ctx = (self.context / self.pillars)[None, :, :, None, :].expand_as(own)
        return (own + ctx).reshape(self.out_features, -1)

    def dense_bias(self) -> torch.Tensor:
        return self.bias.repeat(self.pillars)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, self.dense_weight(), self.dense_bias())


class PillarTiedBatchNorm(nn.BatchNorm1d):
    """BatchNorm over [N, P * units] with statistics and affine shared by the pillars: a pillar that is rarely
    loaded in training is scaled like the others, not blown up by its own small variance."""

    def __init__(self, pillars: int, units: int) -> None:
        super().__init__(units)
        self.pillars = pillars

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = x.shape[0]
        return super().forward(x.reshape(n * self.pillars, -1)).reshape(n, -1)


class PillarPoolLinear(nn.Module):
    """The encoder's second layer: the same map of every pillar's units, averaged over the pillars (a set
    function: no pillar position is special). Linear, so it is written as a dense layer as well."""

    def __init__(self, pillars: int, units: int, out: int) -> None:
        super().__init__()
        self.pillars, self.units, self.out_features = pillars, units, out
        self.weight = nn.Parameter(torch.empty(out, units))
        self.bias = nn.Parameter(torch.zeros(out))
        bound = 1.0 / units**0.5
        nn.init.uniform_(self.weight, -bound, bound)

    def dense_weight(self) -> torch.Tensor:
        """[out, P * units]."""
        return self.weight.repeat(1, self.pillars) / self.pillars

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x, self.dense_weight(), self.bias)


class SlipNet(nn.Module):
    """Encoder MLP -> GRU cell -> predictor MLP -> 2-class softmax. ``forward(x, h) -> (probs, h_next)``.

    ``tied`` = (window, pillars, channels, units) builds the encoder from ``PillarTiedLinear``,
    ``PillarTiedBatchNorm`` and ``PillarPoolLinear`` (one rule for every pillar; training only).
    ``dense_state_dict`` writes such a network in the method's layout, which every other tool reads.
    """

    def __init__(self, input_size: int = 640, hidden: int = 128, enc: int = 1024, pred: tuple[int, int] = (256, 128),
                 aux: int = 0, tied: tuple[int, int, int, int] | None = None):
        super().__init__()
        self.input_size = input_size
        self.hidden = hidden
        self.tied = tied
        if tied is None:
            self.projector = nn.Sequential(
                nn.Linear(input_size, enc), nn.BatchNorm1d(enc), nn.ReLU(),
                nn.Linear(enc, hidden), nn.BatchNorm1d(hidden), nn.ReLU(),
            )
        else:
            window, pillars, channels, units = tied
            if window * pillars * channels != input_size:
                raise ValueError(f"tied encoder {tied} does not read {input_size} inputs")
            self.projector = nn.Sequential(
                PillarTiedLinear(window, pillars, channels, units), PillarTiedBatchNorm(pillars, units), nn.ReLU(),
                PillarPoolLinear(pillars, units, hidden), nn.BatchNorm1d(hidden), nn.ReLU(),
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

    def dense_state_dict(self) -> dict[str, torch.Tensor]:
        """The state dict in the method's layout (dense encoder): what checkpoints store and export reads."""
        state = {k: v.detach().clone() for k, v in self.state_dict().items()}
        if self.tied is None:
            return state
        first, bn, second = self.projector[0], self.projector[1], self.projector[3]
        assert isinstance(first, PillarTiedLinear) and isinstance(bn, PillarTiedBatchNorm)
        assert isinstance(second, PillarPoolLinear)
        with torch.no_grad():
            for key in ("own", "context", "bias"):
                del state[f"projector.0.{key}"]
            state["projector.0.weight"] = first.dense_weight().detach().clone()
            state["projector.0.bias"] = first.dense_bias().detach().clone()
            for key in ("weight", "bias", "running_mean", "running_var"):
                state[f"projector.1.{key}"] = state[f"projector.1.{key}"].repeat(bn.pillars)
            state["projector.3.weight"] = second.dense_weight().detach().clone()
        return state

    def config(self) -> dict:
        """Constructor arguments of the dense layout that ``dense_state_dict`` fills, stored in checkpoints."""
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
