"""CartPole with the pole's length and the push's strength hidden, and two hand-written
controllers as its options (docs/gymnasium.md#your-own-controllers-as-options).

Each episode draws the pole's half-length and the push's force magnitude; they reach
``env.unwrapped`` through :func:`apply`, which also sets what CartPole derives from them in its
constructor (``polemass_length``). The agent sees CartPole's four numbers only (cart position and
velocity, pole angle and angular velocity). The options are controllers a robotics user would
already have, handed in as ``Option(policy=...)``:

* ``left`` and ``right``: a PD balancer of the pole with a small bias, so that it keeps the pole
  up while the cart cruises towards one end of the track (a mobile robot's "go left" and "go
  right" behaviours). An episode ends when the cart leaves the track: here a short one,
  ``|x| > 0.6`` (:data:`TRACK`; CartPole's own is 2.4).

Measured in the raw env (3 reset seeds, 1000 steps, lengths 0.25 / 0.6 / 1.0, forces 5 / 15):
either controller alone runs the cart off the track after 107-1000 steps (most within 110-520;
the weak push drifts faster); handing over to the other one whenever the cart is past 0.3 lasts
the 1000 steps on every one, with 0-5 hand-overs. Which to run is easy; *when to switch* is what
the agent must learn, and it does not see the length or the force that set the drift.

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
TRACK = 0.6
"""How far the cart may go from the centre before the episode ends (CartPole's own: 2.4)."""


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
    """Install an instance on ``CartPoleEnv``: its length, force, the product CartPole caches, and
    this family's short track."""
    env.length = instance["length"]
    env.force_mag = instance["force_mag"]
    env.polemass_length = env.masspole * env.length
    env.x_threshold = TRACK


BIAS = 0.03
"""How far each controller leans its balance point: the speed it cruises at (raw-env figures above)."""


def left(obs, info) -> int:
    """PD on the pole (push towards where it falls; 1: right), balanced so the cart cruises left."""
    return int(obs[2] + 0.3 * obs[3] + 0.1 * obs[1] + BIAS > 0)


def right(obs, info) -> int:
    """The mirror of :func:`left`: the cart cruises right."""
    return int(obs[2] + 0.3 * obs[3] + 0.1 * obs[1] - BIAS > 0)


def family():
    """The family (this package's ``taskvar_torch.families`` entry point)."""
    return gym_family(
        "cartpole_controllers",
        lambda instance: gym.make("CartPole-v1", max_episode_steps=HORIZON),
        instances={
            "train": Cart(),
            "weak": Cart(force_low=5.0, force_high=7.0),
            "strong": Cart(force_low=12.0, force_high=15.0),
        },
        options=[Option("left", policy=left), Option("right", policy=right)],
        instance_via="attributes",
        apply=apply,
        horizon=HORIZON,
        description="CartPole on a short track, pole length and force hidden, two given controllers "
        "(examples/gym_cartpole_controllers)",
    )
