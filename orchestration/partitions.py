"""One dynamic partition per photo; keys are the store's safe photo keys (``assets_store.keys``)."""

from dagster import DynamicPartitionsDefinition

PHOTOS = "photos"
photos = DynamicPartitionsDefinition(name=PHOTOS)
