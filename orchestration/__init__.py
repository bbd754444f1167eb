"""Dagster orchestration: thin wrappers over ``ops``. The only package that imports Dagster."""
