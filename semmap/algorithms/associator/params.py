"""The landmark mapper's parameters: the `associator:` section of the configuration (semmap/core/config/associator.py,
where every threshold is defined once with its default and range)."""

from semmap.core.config.associator import MapperParams, PriorParams

__all__ = ["MapperParams", "PriorParams"]
