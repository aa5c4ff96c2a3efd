"""Prefect flows. They call the same functions as the DVC stages (``plad.stages``)."""
