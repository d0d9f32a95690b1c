"""The only layer that knows Hydra or a run folder: the ``flamerecon`` command, config ->
options, run folder, hook (TensorBoard, checkpoints, resume, guard), lock, summary, and the
scripts' shared command-line helpers."""
