"""Deploying a cut-off policy on a real rig.

- :class:`~pneugym.deploy.controller.Controller`: raw sensor samples in (time, position,
  absolute port pressures), the valve command out; the same decisions as the policy inside the
  environment, bit for bit;
- :func:`~pneugym.deploy.replay.replay`: a controller run offline over measured runs
  (``pneugym-measurement/1``): when it would have cut, and what the model predicts that cut saves;
- :mod:`~pneugym.deploy.export`: a neural policy's network to ONNX (onnxruntime) or to a
  numpy-only runtime.
"""
from .controller import Controller, SampleError

__all__ = ["Controller", "SampleError"]
