"""The command-line binaries (``python -m experiments.<name>``). Importing the package first
quiets TensorFlow's start-up log (:mod:`stnh_tf.startup`; ``STNH_VERBOSE=1`` shows it)."""

from stnh_tf import startup as _startup

_startup.quiet_binary_startup()
