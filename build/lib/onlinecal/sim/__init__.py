"""Simulator: the paper's 3-D rotation platform session and flight profiles (a generic flight, a
multirotor and a fixed-wing from vehicle physics), with truth."""

from .sensors import PROFILES, ProfileError, Simulation, Truth, paper_truth, parse_profile, simulate

__all__ = ["PROFILES", "ProfileError", "Simulation", "Truth", "paper_truth", "parse_profile", "simulate"]
