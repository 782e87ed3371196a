"""A small user task for the tests: localisation's world, success = robots within half the range."""
import numpy as np

from sim.tasks import Metric
from sim.tasks.localisation import Localisation


class NearBeacon(Localisation):
    name = "near_beacon"
    version = 2
    success_label = "fraction of robots near the beacon"
    robot_label = "near"
    primary_metric = "final_near"
    metrics = (Metric("final_near", "final near"), Metric("return", "return"))

    def step_info(self, env):
        near = env.target_dist <= 0.5 * env.cfg.comm_radius_mm
        return {"near": near, "success": near.mean(axis=1), "robot_success": near}

    def reward(self, env, u, info):
        return info["success"].astype(np.float32)
