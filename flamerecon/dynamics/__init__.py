"""Dynamics: what a reconstructed sequence does between its frames. Velocities fitted to the
next frame's images and advection (flow.py), one frame with its neighbours' views carried onto
it (motion.py), future frames predicted and scored (prediction.py). Above ``fit/`` and
``evaluate/`` (it reconstructs frames and scores them), below ``run/``; the warp itself is an
operator (:mod:`flamerecon.operators.warp`)."""
