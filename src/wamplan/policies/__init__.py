"""Policies: the interface, and the scripted ones that generate data (expert, noisy expert, pink noise)."""

from wamplan.policies.base import ACTION_DIM, CAMERAS, POLICIES, PROPRIO_DIM, Observation, Policy, make_policy, register_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy
from wamplan.policies.noise import NoisyExpertConfig, NoisyExpertPolicy, PinkNoiseConfig, PinkNoisePolicy

__all__ = ["ACTION_DIM", "CAMERAS", "POLICIES", "PROPRIO_DIM", "Observation", "Policy", "make_policy", "register_policy",
           "ExpertConfig", "ExpertPolicy", "NoisyExpertConfig", "NoisyExpertPolicy", "PinkNoiseConfig", "PinkNoisePolicy"]
