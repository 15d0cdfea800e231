"""A SIR step recorded once as a CUDA graph and replayed every frame.

On a GPU a batched SIR step of a few hundred thousand particles is a few hundred microseconds of
kernels behind milliseconds of Python and kernel launches: :func:`~torchtrack.filter.sir_step`
at (B, N) = (100, 1000) takes ~3 ms on an H200 of which the device works ~0.6 ms
(``tools/bench_gpu.py --profile``). :class:`GraphedSIR` records the same step (the same
``sir_step`` code: resampling, motion, likelihood, normalisation, estimate) with
``torch.cuda.graph`` and replays it, and feeds each step's particles back to the next inside the
graph, so a frame costs one replay and one read of a check value.

What a graph needs, and what this class asks of its caller:

* **Fixed shapes and buffers.** B, N, D, the scheme and the estimator are fixed at capture. The
  likelihood must read its frame from buffers that stay where they are: give it the new frame in
  place (e.g. :meth:`torchtrack.observe.haar_box.HaarBoxLikelihood.set_frame`, which copies a
  frame of the same size into its buffer), not by rebinding a tensor.
* **One generator** on the GPU (or ``None``: torch's default CUDA generator); its stream is
  registered with the graph, so each replay draws new numbers from it.
* **No reads back to the host inside the step.** While the graph is recorded the value checks of
  ``sir_step`` (NaN or ``+inf`` likelihoods, weights without mass) cannot run; instead, after
  each replay, one read of the new log-weights' sum raises the same ``FilterError`` when the
  likelihood produced NaN or ``+inf`` (``check=False`` skips that read). Rows whose likelihood
  is zero everywhere restart uniform, as in ``sir_step``.
"""

from __future__ import annotations

import math

import torch

from torchtrack.errors import ConfigError, FilterError
from torchtrack.filter.particles import check_particles
from torchtrack.filter.sir import Likelihood, MotionFn, StepResult, sir_step

__all__ = ["GraphedSIR"]

#: eager steps on a side stream before recording (CUDA libraries initialise lazily)
_WARMUP = 3


class GraphedSIR:
    """``sir_step`` on CUDA tensors, recorded once and replayed.

    Args:
        states: ``(B, N, D)`` CUDA particles to start from (copied: the graph owns its buffers).
        log_weights: ``(B, N)`` their log-weights.
        motion, likelihood: as for :func:`~torchtrack.filter.sir_step`; the likelihood reads its
            frame from buffers updated in place between steps.
        scheme, estimator, log_likelihood: as for ``sir_step`` (resampling every step).
        generator: a CUDA ``torch.Generator`` or ``None`` (the default CUDA generator).
        check: after each replay, read the log-weights' sum once and raise ``FilterError`` on
            NaN or ``+inf`` (the likelihood's fault); ``False`` never waits for the device.

    Each :meth:`step` advances the filter one frame and returns a :class:`StepResult` whose
    tensors are the graph's own buffers, overwritten by the next step (clone what you keep).
    The warm-up before recording runs three eager steps from ``states``, which draw from the
    generator but do not move the filter.

    Raises:
        ConfigError: the tensors are not on a CUDA device, or the generator is not a CUDA
            generator on that device.
        ShapeError: as ``sir_step``.
    """

    def __init__(
        self,
        states: torch.Tensor,
        log_weights: torch.Tensor,
        motion: MotionFn,
        likelihood: Likelihood,
        *,
        scheme: str = "systematic",
        estimator: str = "mean",
        log_likelihood: bool = True,
        generator: torch.Generator | None = None,
        check: bool = True,
    ) -> None:
        check_particles(states, log_weights)
        if states.device.type != "cuda" or log_weights.device != states.device:
            raise ConfigError(
                "GraphedSIR records a CUDA graph: states and log_weights must be on one CUDA "
                f"device, got {states.device} and {log_weights.device} (use sir_step elsewhere)"
            )
        if generator is not None and (
            not isinstance(generator, torch.Generator) or generator.device.type != "cuda"
        ):
            got = generator.device if isinstance(generator, torch.Generator) else generator
            raise ConfigError(
                f"GraphedSIR draws inside the graph: generator must be one CUDA torch.Generator "
                f"or None, got {got}"
            )
        self.check = bool(check)
        self._states = states.detach().clone()
        self._log_weights = log_weights.detach().clone()

        def body() -> StepResult:
            return sir_step(
                self._states,
                self._log_weights,
                motion,
                likelihood,
                log_likelihood=log_likelihood,
                scheme=scheme,
                estimator=estimator,
                generator=generator,
            )

        side = torch.cuda.Stream(device=states.device)
        side.wait_stream(torch.cuda.current_stream(states.device))
        with torch.cuda.stream(side):
            for _ in range(_WARMUP):  # the checks run here, eagerly: bad inputs fail now
                body()
        torch.cuda.current_stream(states.device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        if generator is not None:
            register = getattr(self.graph, "register_generator_state", None)
            if register is None:  # torch before 2.5
                raise ConfigError(
                    f"this torch ({torch.__version__}) cannot draw from a given generator inside "
                    "a CUDA graph: pass generator=None (the default CUDA generator)"
                )
            register(generator)
        with torch.cuda.graph(self.graph):
            out = body()
            # the step's particles are the next step's input, without leaving the device
            self._states.copy_(out.states)
            self._log_weights.copy_(out.log_weights)
        self._out = out

    def set_particles(self, states: torch.Tensor, log_weights: torch.Tensor) -> None:
        """Restart from ``states (B, N, D)`` / ``log_weights (B, N)`` (copied into the graph's
        buffers; the shapes of the capture)."""
        check_particles(states, log_weights)
        if states.shape != self._states.shape:
            raise ConfigError(
                f"GraphedSIR was recorded for states {tuple(self._states.shape)}, got "
                f"{tuple(states.shape)}: record another one for a new shape"
            )
        self._states.copy_(states)
        self._log_weights.copy_(log_weights)

    def step(self) -> StepResult:
        """One SIR step on the current frame (the likelihood's buffers): replay the graph."""
        self.graph.replay()
        if self.check:
            total = float(self._out.log_weights.sum())  # the one read of the step
            if math.isnan(total) or total == math.inf:
                raise FilterError(
                    "GraphedSIR step: the likelihood returned NaN or +inf (weights cannot be "
                    "normalised); the filter's particles are not valid any more"
                )
        return self._out
