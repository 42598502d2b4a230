"""Measurements that drive the environment, the policy and the shield
together: the deterministic deployment loop (``deployment``) and the
predictor-honesty check of the safety rows (``honesty``)."""
