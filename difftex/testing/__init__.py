"""Scenes and references shared by difftex's tests and experiments (not part of the differentiable API)."""
