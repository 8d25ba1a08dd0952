"""Planner: the bagging goal (g†, g*) and the SOI path g0 -> g† -> g* (CBiRRT and baselines)."""

from bagit.services.planner.goal import BaggingGoal, bagging_soi
from bagit.services.planner.plan import PlanResult, collision_model, plan, plan_path, plan_scenario
from bagit.services.planner.rrt import PLANNERS

__all__ = ["BaggingGoal", "bagging_soi", "PlanResult", "plan", "plan_path", "plan_scenario", "collision_model", "PLANNERS"]
