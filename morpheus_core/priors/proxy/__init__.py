"""The weight-free proxy prior: ``prior`` (``ProxyPrior``, its corruptions) and ``shape`` (``InflatedProxy``, the
object inflated from the photo's silhouette, meshed in ``meshing``). Import from those modules."""
