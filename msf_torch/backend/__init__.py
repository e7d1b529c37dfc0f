"""Batched Levenberg-Marquardt back end over the residuals of :mod:`msf_torch.sensors`.

``variables`` (kinds of variables and their retraction), ``factors`` (factor types),
``robust`` (M-estimators), ``problem`` (variable table and normal equations), ``lm`` (the
batched solver, dense and sparse), ``preintegration`` (IMU and wheel increments between
keyframes), ``window`` (keyframe smoothers: full batch and sliding window with
marginalisation).
"""
