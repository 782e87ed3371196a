"""Write the shipped hand-written policies (no training: their parameters are in the code) to export/data/.

    python -m tools.ship_rules

``searcher_policy.npz`` and ``pusher_policy.npz`` (localisation: sim.baselines' TUNED["kilobot"] searcher, and
with sim.baselines.PUSHER) and ``aggregator_policy.npz`` (aggregation: sim.tasks.aggregation's tuned
AggregatorParams), ``stop_in_light_policy.npz`` and ``run_and_tumble_policy.npz`` (phototaxis: sim.tasks.phototaxis'
tuned StopInLightParams and RunAndTumbleParams) and ``shadow_pusher_policy.npz`` (transport: sim.tasks.transport's
tuned ShadowPusherParams), each in its task's kilobot world. The files are byte-for-byte
reproducible; run this after a change of a preset or of the parameters (tests/test_searcher_firmware.py,
tests/test_aggregator_firmware.py, tests/test_light_rule_firmware.py and tests/test_shadow_pusher_firmware.py fail on a
stale file).
"""
from __future__ import annotations

import sys
from pathlib import Path

from kiloforge.actors.aggregator import aggregator_policy
from kiloforge.actors.run_and_tumble import run_and_tumble_policy
from kiloforge.actors.searcher import pusher_policy, searcher_policy
from kiloforge.actors.shadow_pusher import shadow_pusher_policy
from kiloforge.actors.stop_in_light import stop_in_light_policy
from kiloforge.policies import save_policy
from sim.config import preset

DATA = Path(__file__).resolve().parents[1] / "export" / "data"


def rule_policies() -> dict:
    """File name -> the shipped hand-written policy it holds."""
    world = preset("kilobot")
    return {"searcher_policy.npz": searcher_policy(world), "pusher_policy.npz": pusher_policy(world),
            "aggregator_policy.npz": aggregator_policy(world), "stop_in_light_policy.npz": stop_in_light_policy(world),
            "run_and_tumble_policy.npz": run_and_tumble_policy(world), "shadow_pusher_policy.npz": shadow_pusher_policy(world)}


def main() -> int:
    for name, policy in rule_policies().items():
        save_policy(policy, DATA / name)
        print(f"wrote {DATA / name} (hash {policy.hash})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
