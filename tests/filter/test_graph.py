"""GraphedSIR: the SIR step recorded as a CUDA graph (CUDA tests run on a GPU machine,
``tools/gpu_check.sh``)."""

from __future__ import annotations

import pytest
import torch

from torchtrack.errors import ConfigError, FilterError
from torchtrack.filter import KleinAR, sir_step, uniform_log_weights
from torchtrack.filter.graph import GraphedSIR

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available (no GPU)")


def _gaussian(target: torch.Tensor, motion: KleinAR, sd: float = 4.0):
    """Log-likelihood of boxes around ``target (4,)``, read from its buffer at every call."""

    def lik(states):
        d = motion.to_boxes(states) - target
        return -(d * d).sum(-1) / (2 * sd * sd)

    return lik


def test_cpu_tensors_are_refused():
    m = KleinAR()
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]]), 50, torch.Generator().manual_seed(0))
    with pytest.raises(ConfigError, match="must be on one CUDA device"):
        GraphedSIR(x, uniform_log_weights(x), m, lambda s: s[..., 0] * 0)


@CUDA
def test_a_cuda_generator_is_required():
    m = KleinAR()
    g = torch.Generator(device="cuda").manual_seed(0)
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]], device="cuda"), 50, g)
    with pytest.raises(ConfigError, match=r"one CUDA torch\.Generator"):
        GraphedSIR(
            x, uniform_log_weights(x), m, lambda s: s[..., 0] * 0, generator=torch.Generator()
        )


@CUDA
def test_replays_follow_a_moving_target_as_the_eager_step_does():
    m = KleinAR()
    start = torch.tensor([[100.0, 80.0, 30.0, 60.0]] * 4, device="cuda")
    target = start[0].clone()
    lik = _gaussian(target, m)
    g = torch.Generator(device="cuda").manual_seed(0)
    x = m.init(start, 500, g)
    graphed = GraphedSIR(x, uniform_log_weights(x), m, lik, generator=g)
    ge = torch.Generator(device="cuda").manual_seed(1)
    eager = sir_step(x, uniform_log_weights(x), m, lik, generator=ge)
    for t in range(30):
        target[0] = 100.0 + 2.0 * t  # the frame's observation, updated in place
        r = graphed.step()
        eager = sir_step(eager.states, eager.log_weights, m, lik, generator=ge)
        est, ref = m.to_boxes(r.estimate), m.to_boxes(eager.estimate)
        assert est.shape == (4, 4) and est.device.type == "cuda"
        assert float((est - target).abs().max()) < 6.0  # on the target, every row
        assert float((est - ref).abs().max()) < 6.0  # and where the eager filter is
    assert bool(torch.isclose(r.log_weights.exp().sum(1), torch.ones(4, device="cuda")).all())
    # restart elsewhere: the same graph, new particles
    target[:2] = torch.tensor([300.0, 200.0], device="cuda")
    y = m.init(target.repeat(4, 1), 500, g)
    graphed.set_particles(y, uniform_log_weights(y))
    for _ in range(5):
        r = graphed.step()
    assert float((m.to_boxes(r.estimate) - target).abs().max()) < 6.0
    with pytest.raises(ConfigError, match="recorded for states"):
        graphed.set_particles(y[:2], uniform_log_weights(y[:2]))


@CUDA
def test_nan_likelihood_after_recording_is_a_filter_error():
    m = KleinAR()
    g = torch.Generator(device="cuda").manual_seed(0)
    x = m.init(torch.tensor([[50.0, 50.0, 20.0, 20.0]], device="cuda"), 100, g)
    poison = torch.zeros((), device="cuda")

    def lik(states):
        return -states[..., 0].abs() * 0.01 + poison

    graphed = GraphedSIR(x, uniform_log_weights(x), m, lik, generator=g)
    graphed.step()
    poison.fill_(float("nan"))
    with pytest.raises(FilterError, match="NaN or \\+inf"):
        graphed.step()
