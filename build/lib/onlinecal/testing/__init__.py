"""Test vehicles and fixtures: never imported by the production code (``onlinecal.io``, ``onlinecal.ukf``)."""
