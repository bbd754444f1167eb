"""The Morpheus3D method: tensors in, tensors out. Imports neither Dagster nor the store."""
