"""Learned functions on (x0, x1): cost-to-go J, steering parameters U, validity V."""

from rrtcolearn.learn.models import (
    CostToGoRegressor,
    LearnedFunctions,
    SteeringRegressor,
    ValidityClassifier,
)
from rrtcolearn.learn.neighbours import NeighbourIndex

__all__ = [
    "CostToGoRegressor",
    "LearnedFunctions",
    "NeighbourIndex",
    "SteeringRegressor",
    "ValidityClassifier",
]
