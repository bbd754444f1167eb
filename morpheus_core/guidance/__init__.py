"""The method's guidance: the DCT and band masks, the diffusion schedule, hybrid guidance (Algorithm 1),
the stages' guidance settings and the loss balance."""
