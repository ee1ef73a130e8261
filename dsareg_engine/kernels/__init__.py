"""What the numba kernels of every part share: one compiler per kernel group at a time
(:mod:`.compile_lock`).

Kept apart from :mod:`dsareg_engine.render` (whose package imports torch): a volume reading in the service's
validator waits for its kernels without loading torch.
"""
