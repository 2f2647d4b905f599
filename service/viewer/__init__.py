"""The viewer's data and its three ways to open: ``panogs view``, the service's ``/app`` and ``panogs export-html``."""
