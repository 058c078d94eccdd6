"""Policies: the interface, and the scripted ones that generate data (expert, noisy expert, pink noise,
demonstration replay). A task's observation and action spaces are in its spec (``wamplan.envs.spec.TaskSpec``)."""

from wamplan.policies.base import POLICIES, Policy, make_policy, register_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy
from wamplan.policies.noise import NoisyExpertConfig, NoisyExpertPolicy, PinkNoiseConfig, PinkNoisePolicy

__all__ = ["POLICIES", "Policy", "make_policy", "register_policy", "ExpertConfig", "ExpertPolicy",
           "NoisyExpertConfig", "NoisyExpertPolicy", "PinkNoiseConfig", "PinkNoisePolicy"]
