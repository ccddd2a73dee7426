"""Simulator: the paper's 3-D rotation platform session and a flight profile, with truth."""

from .sensors import Simulation, Truth, paper_truth, simulate

__all__ = ["Simulation", "Truth", "paper_truth", "simulate"]
