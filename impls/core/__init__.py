"""Backend-independent algorithms, written once against the array API (``xp``).

Every backend binds these to its own pieces — how φ is evaluated and differentiated (autodiff,
or finite differences in numpy) and how the per-ray loop runs (active-set compaction in numpy
and torch, fixed-shape masked ``lax.while_loop`` over ray chunks in jax) — so the *meaning* of
a method is defined in exactly one place and the three backends agree by construction.
"""
