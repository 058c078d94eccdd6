"""Policies: the interface, and the scripted ones that generate data (expert, noisy expert, pink noise).
The task's observation and action spaces are in ``wamplan.envs.contract``."""

from wamplan.policies.base import POLICIES, Policy, make_policy, register_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy
from wamplan.policies.noise import NoisyExpertConfig, NoisyExpertPolicy, PinkNoiseConfig, PinkNoisePolicy

__all__ = ["POLICIES", "Policy", "make_policy", "register_policy", "ExpertConfig", "ExpertPolicy",
           "NoisyExpertConfig", "NoisyExpertPolicy", "PinkNoiseConfig", "PinkNoisePolicy"]
