"""How the method runs on a device: device choice, execution settings, CUDA graphs, Triton support,
on-device step skipping, cheap gathers, atomic writes."""
