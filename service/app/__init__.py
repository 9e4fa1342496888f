"""The application layer: what the HTTP routes, the gRPC server and the CLI call.

:mod:`~service.app.services` (the process's store, model cache and synthesis slots),
:mod:`~service.app.operations` (one function per operation: check the state, parse the
upload, store it, queue jobs), :mod:`~service.app.uploads` (bounded parsing of untrusted
payloads), :mod:`~service.app.synthesis` and :mod:`~service.app.retiming` (synchronous
requests), :mod:`~service.app.input_rigs`, :mod:`~service.app.schemas` (the resource models of
the contract), :mod:`~service.app.limits`. Nothing here knows HTTP.
"""
