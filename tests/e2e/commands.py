"""The ``facesynth`` commands of a multi-machine deployment: the API without an embedded
worker, and workers of one job thread each. The end-to-end test starts exactly these
(:mod:`tests.e2e.conftest`) and ``docker/compose.yaml`` runs exactly these
(checked by ``tests/test_docker.py``)."""

#: ``facesynth serve --workers 0``: HTTP + gRPC, jobs go to the shared queue
API_COMMAND = ("serve", "--workers", "0")
#: ``facesynth worker --workers 1``: one job thread per process (scale by processes)
WORKER_COMMAND = ("worker", "--workers", "1")
