"""Pictures of a run: filmstrip, video and plots (see :mod:`neuromotor.viz.render`)."""
