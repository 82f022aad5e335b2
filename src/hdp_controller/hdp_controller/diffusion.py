"""A trajectory DDPM that predicts x0, with inpainting and classifier-free guidance.

The noise schedules and samplers are diffusers' (a well-kept library):
training and the default sampler are DDPM with the cosine schedule over
100 steps ("squaredcos_cap_v2"); DDIM over fewer steps is the fast sampler.
Both read the network's output as x0 (prediction_type="sample"), which
the paper found better than predicting the noise.

Inpainting (Diffuser): the waypoints fixed by the task (the start, and
for the pose diffuser the goal) are overwritten with their known values in
the network's input and output at every step, so they hold exactly. A
constraint that is not a known waypoint (the joint diffuser's goal is a pose,
not joints) can be imposed the same way by ``guide``, a map applied to every
step's x0 prediction: the next step denoises from the corrected estimate.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from diffusers import DDIMScheduler, DDPMScheduler
from torch import nn

SAMPLERS = ('ddpm', 'ddim')


def make_scheduler(sampler: str, train_steps: int):
    kwargs = dict(num_train_timesteps=train_steps, beta_schedule='squaredcos_cap_v2',
                  prediction_type='sample', clip_sample=False)
    if sampler == 'ddpm':
        return DDPMScheduler(**kwargs)
    if sampler == 'ddim':
        return DDIMScheduler(**kwargs)
    raise ValueError(f'unknown sampler {sampler!r}; choose from {SAMPLERS}')


def inpaint(x: torch.Tensor, known: dict[int, torch.Tensor]) -> torch.Tensor:
    """x (B, T, D) with waypoints ``known`` (index -> (B, D)) overwritten."""
    x = x.clone()
    for index, value in known.items():
        x[:, index] = value
    return x


class TrajectoryDiffusion(nn.Module):
    """Wraps a denoiser ``net(x_t (B, T, D), t (B,), cond (B, C), local (B, T, L) | None) -> x0 (B, T, D)``."""

    def __init__(self, net: nn.Module, horizon: int, dim: int, train_steps: int = 100):
        super().__init__()
        self.net, self.horizon, self.dim, self.train_steps = net, horizon, dim, train_steps
        self.noise_schedule = make_scheduler('ddpm', train_steps)

    def predict_x0(self, x_t, t, cond, known, local=None):
        return inpaint(self.net(inpaint(x_t, known), t, cond, local), known)

    def loss(self, x0: torch.Tensor, cond: torch.Tensor, known: dict, local: torch.Tensor | None = None,
             t: torch.Tensor | None = None, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """MSE of the x0 prediction from step t (B,) after adding noise (B, T, D) (both drawn
        when not given); returns (loss, predicted x0 (B, T, D))."""
        t = torch.randint(0, self.train_steps, (x0.shape[0],), device=x0.device) if t is None else t
        noise = torch.randn_like(x0) if noise is None else noise
        x_t = self.noise_schedule.add_noise(x0, noise, t)
        x0_hat = self.predict_x0(x_t, t, cond, known, local)
        return nn.functional.mse_loss(x0_hat, x0), x0_hat

    @torch.no_grad()
    def sample(self, cond: torch.Tensor, known: dict, null_cond: torch.Tensor | None = None,
               guidance: float = 1.0, sampler: str = 'ddpm', steps: int | None = None,
               generator: torch.Generator | None = None, local: torch.Tensor | None = None,
               guide: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
        """(B, T, D) trajectories from Gaussian noise.

        With ``null_cond`` (the conditions with the dropped ones nulled, as in
        training) and guidance w != 1: x0 = x0_null + w (x0_cond - x0_null).
        ``guide`` (B, T, D) -> (B, T, D) corrects each step's x0 estimate (the last
        step's is the sample).
        """
        scheduler = make_scheduler(sampler, self.train_steps)
        scheduler.set_timesteps(steps or self.train_steps)
        b = cond.shape[0]
        # Drawn on the CPU (the generator's device) so a seed gives the same noise on any device.
        x = torch.randn(b, self.horizon, self.dim, generator=generator).to(cond.device)
        guided = null_cond is not None and guidance != 1.0
        for t in scheduler.timesteps:
            steps_t = torch.full((b,), int(t), device=cond.device)
            if guided:
                both = self.predict_x0(torch.cat([x, x]), torch.cat([steps_t, steps_t]),
                                       torch.cat([cond, null_cond]), {i: torch.cat([v, v]) for i, v in known.items()},
                                       None if local is None else torch.cat([local, local]))
                x0_cond, x0_null = both.chunk(2)
                x0 = x0_null + guidance * (x0_cond - x0_null)
            else:
                x0 = self.predict_x0(x, steps_t, cond, known, local)
            if guide is not None:
                x0 = inpaint(guide(x0), known)
            x = scheduler.step(x0, t, x, generator=generator).prev_sample
        return inpaint(x, known)
