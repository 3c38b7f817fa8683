"""Comparison controllers from the contouring literature (see :mod:`oga.controllers.base`)."""

__all__: list[str] = []
