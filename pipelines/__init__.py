"""Composition of perception, estimation and mapping: the pipelines and the ``octofactor`` CLI."""
