"""The service's contract with its clients, defined once.

* :mod:`service.contract.names`: the vocabulary (methods, image modes, poses, job
  statuses, subject orders and statuses, problem types) and the rule for whether a subject is
  attached. Standard library only: the CLI imports it before numpy.
* :mod:`service.contract.result`: pydantic models of the result document (``GET
  /v1/jobs/{id}/result`` and its subjects, transforms, similarity), the routes'
  ``response_model`` and what :mod:`service.client` and :mod:`service.plots` read.
"""
