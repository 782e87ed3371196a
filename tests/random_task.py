"""A test task: aggregation with the ``random`` observation feature (symmetry breaking), for --task path:Class."""
from sim.tasks.aggregation import Aggregation


class RandomAggregation(Aggregation):
    name = "aggregation_random"
    features = ("wall", "rbf", "random")
