"""The baselines stage's plan, without training anything: which agent the pool starts first."""

from schemas.config import RandomiseConfig, RenderConfig
from stages.baselines import RLUnit, longest_first


def _unit(algorithm: str, family: str, env_steps: int) -> RLUnit:
    return RLUnit(unit_key=f"baselines-{algorithm}-{family}", algorithm=algorithm, family=family, tasks=[],
                  embeddings={}, render=RenderConfig(), randomise=RandomiseConfig(), env_steps=env_steps,
                  replay_size=50_000, checkpoint_every=25_000, seed=0, path="unused")


def test_sac_and_the_larger_budgets_start_first():
    # rl_units' order (algorithm, then family): the generalist's budgets per family
    planned = [_unit("ppo", "metaworld", 382_023), _unit("ppo", "navigation", 254_522),
               _unit("ppo", "robosuite", 455_956), _unit("sac", "metaworld", 382_023),
               _unit("sac", "robosuite", 455_956)]
    order = [(u.algorithm, u.family) for u in longest_first(planned)]
    assert order == [("sac", "robosuite"), ("sac", "metaworld"), ("ppo", "robosuite"), ("ppo", "metaworld"),
                     ("ppo", "navigation")]
    assert [u.unit_key for u in planned][0] == "baselines-ppo-metaworld"  # a new list; the caller's unchanged
