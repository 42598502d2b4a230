"""The actors' policy: hard oblique trees (numpy; torch twin in
``tree_torch``), the bounded proposal, the SAIL proposal map and the actor's
per-step proposal chain (``rollout.propose``). Numpy-only unless a ``*_torch``
module or a torch function of ``sail``/``proposal`` is used."""
