"""regtree.service: the web service around :mod:`registration`.

FastAPI app (:func:`service.main.create_app`), SQLAlchemy models, a durable job queue with
leases, worker processes, and the ``regtree`` command line.
"""

__version__ = "0.1.0"
