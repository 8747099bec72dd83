#!/usr/bin/env python3
"""PyTorch's time for the recurrent PPO minibatch step that
`cargo bench -p host-trainer --bench recurrent_update` times (issue [lstm-speed], item 4).

Row G's actor and critic (each a 2-layer LSTM of 128, then an MLP 256-128-128-64 with tanh;
4 means and a learned log sigma, or one value) on one minibatch of SEQUENCES windows of STEPS
steps of 30 observations: the LSTMs over the whole window from stored states (one
`nn.LSTM` call per network: the fastest form PyTorch has, with no episode-end masks, which
RSL-RL gets by splitting trajectories at dones and padding), the heads on every sample, the
clipped surrogate with the Gaussian log-likelihood, the entropy bonus, the clipped value
loss, one backward pass, the global gradient-norm clip and Adam: what RSL-RL 2.2.4's
`PPO.update` does per minibatch. Prints the median of --repeats steps after two warm-up
steps, on --threads threads (default 2, the machine's cores).

    python3 tools/recurrent_update_torch.py [--sequences 256] [--steps 100] [--threads 2]
"""

import argparse
import platform
import statistics
import time

import torch
from torch import nn


class Net(nn.Module):
    def __init__(self, obs, out):
        super().__init__()
        self.lstm = nn.LSTM(obs, 128, num_layers=2)
        widths = [128, 256, 128, 128, 64]
        layers = []
        for a, b in zip(widths, widths[1:]):
            layers += [nn.Linear(a, b), nn.Tanh()]
        layers.append(nn.Linear(64, out))
        self.head = nn.Sequential(*layers)

    def forward(self, x, state):
        y, _ = self.lstm(x, state)
        return self.head(y.reshape(-1, 128))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", type=int, default=256)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=10)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    t, b, obs = a.steps, a.sequences, 30
    actor, critic = Net(obs, 4), Net(obs, 1)
    log_std = nn.Parameter(torch.zeros(4))
    params = list(actor.parameters()) + [log_std] + list(critic.parameters())
    optim = torch.optim.Adam(params, lr=1e-5)
    x = torch.rand(t, b, obs) * 2 - 1
    state = lambda: (torch.rand(2, b, 128) - 0.5, torch.rand(2, b, 128) - 0.5)  # noqa: E731
    h_actor, h_critic = state(), state()
    n = t * b
    actions = torch.rand(n, 4) * 2 - 1
    old_log_prob = torch.rand(n) - 4.0
    advantages = torch.randn(n)
    old_values = torch.randn(n)
    returns = torch.randn(n)
    clip = 0.2

    def step():
        mean = actor(x, h_actor)
        dist = torch.distributions.Normal(mean, log_std.exp())
        log_prob = dist.log_prob(actions).sum(-1)
        ratio = torch.exp(log_prob - old_log_prob)
        surrogate = torch.max(-advantages * ratio,
                              -advantages * ratio.clamp(1 - clip, 1 + clip)).mean()
        value = critic(x, h_critic).squeeze(-1)
        clipped = old_values + (value - old_values).clamp(-clip, clip)
        value_loss = torch.max((value - returns) ** 2, (clipped - returns) ** 2).mean()
        loss = surrogate + value_loss - 0.008 * dist.entropy().sum(-1).mean()
        optim.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(params, 1.0)
        optim.step()

    for _ in range(2):
        step()
    times = []
    for _ in range(a.repeats):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{a.threads} threads: {b} x {t} minibatch step median {median * 1e3:.0f} ms "
          f"(min {min(times) * 1e3:.0f}, max {max(times) * 1e3:.0f}), "
          f"{n / median / 1e3:.1f} k samples/s")


if __name__ == "__main__":
    main()
