"""CartPole with the pole's length and the push's strength hidden, and two hand-written
controllers as its options (docs/gymnasium.md#your-own-controllers-as-options).

Each episode draws the pole's half-length and the push's force magnitude; they reach
``env.unwrapped`` through :func:`apply`, which also sets what CartPole derives from them in its
constructor (``polemass_length``). The agent sees CartPole's four numbers only (cart position and
velocity, pole angle and angular velocity). The options are controllers a robotics user would
already have, handed in as ``Option(policy=...)``:

* ``upright``: a PD balancer of the pole alone (angle and angular velocity); it keeps the pole up
  but lets the cart drift, and an episode also ends when the cart leaves the track (``|x| > 2.4``).
* ``centre``: a full-state linear controller (cart position and velocity too), which brings the
  cart back but is tuned for short poles: on a pole of length 1 it drops it within 20 steps.

Measured in the raw env (6 reset seeds, 1000 steps, lengths 0.25 / 0.6 / 1.0, forces 5 / 15):
``upright`` holds the pole but drifts off the track after 900-1000 steps on every one; ``centre``
lasts the 1000 steps on lengths up to 0.6 and 11-20 steps on length 1.0. No controller is best on
every instance, and the agent does not see the length: which to run, and when to switch, is what
it learns.

Neither knows the instance. taskvar_torch learns, across the family, the value of running each
controller from each state (``Q^mu_bar``) and when one is worth more than the other (the max-value
head): the options method runs the better-looking controller until it terminates (never, here:
only the episode's end ends it), interruption switches as soon as the other one looks better
(paper §3.3, Algorithm 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym

from taskvar_torch.families.gymnasium import Option, gym_family

HORIZON = 1000
"""Steps an episode may last (CartPole-v1 stops at 500; here the cart's drift matters)."""


@dataclass(frozen=True)
class Cart:
    """``length ~ U[length_low, length_high]``, ``force ~ U[force_low, force_high]``
    (``--shift env.instances.FIELD=...``)."""

    length_low: float = 0.25
    length_high: float = 1.0
    force_low: float = 5.0
    force_high: float = 15.0

    def __post_init__(self):
        if not 0 < self.length_low <= self.length_high or not 0 < self.force_low <= self.force_high:
            raise ValueError(f"need 0 < low <= high for length and force, got {self}")

    def sample(self, rng):
        return {
            "length": float(rng.uniform(self.length_low, self.length_high)),
            "force_mag": float(rng.uniform(self.force_low, self.force_high)),
        }


def apply(env, instance):
    """Install an instance on ``CartPoleEnv``: its length, force, and the product CartPole caches."""
    env.length = instance["length"]
    env.force_mag = instance["force_mag"]
    env.polemass_length = env.masspole * env.length


def upright(obs, info) -> int:
    """PD on the pole: push towards where it falls (1: right)."""
    return int(obs[2] + 0.3 * obs[3] > 0)


def centre(obs, info) -> int:
    """Full-state linear feedback (signs as an LQR gain of the linearised cart-pole)."""
    x, x_dot, theta, theta_dot = (float(v) for v in obs)
    return int(0.1 * x + 0.3 * x_dot + theta + 0.3 * theta_dot > 0)


def family():
    """The family (this package's ``taskvar_torch.families`` entry point)."""
    return gym_family(
        "cartpole_controllers",
        lambda instance: gym.make("CartPole-v1", max_episode_steps=HORIZON),
        instances={
            "train": Cart(),
            "long_weak": Cart(0.8, 1.0, 5.0, 7.0),
            "short_strong": Cart(0.25, 0.4, 12.0, 15.0),
        },
        options=[Option("upright", policy=upright), Option("centre", policy=centre)],
        instance_via="attributes",
        apply=apply,
        horizon=HORIZON,
        description="CartPole, pole length and force hidden, two given controllers "
        "(examples/gym_cartpole_controllers)",
    )
