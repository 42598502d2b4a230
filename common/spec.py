"""Team constants every layer shares, defined once.

The team is three carriers (robots, or two robots and a human). A carrier's
action is ``(v_x, v_y, omega)`` in its own body frame, normalized to
``[-1, 1]``; the joint action the shield's QP optimizes stacks the three
blocks, carrier ``i`` in columns ``CARRIER_ACT_DIM * i ... CARRIER_ACT_DIM * (i + 1)``.
"""
N_CARRIERS = 3
CARRIER_ACT_DIM = 3
JOINT_ACT_DIM = N_CARRIERS * CARRIER_ACT_DIM   # d = 9: the QP variable (Eq. qpshield)
