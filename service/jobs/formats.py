"""The result formats of a synthesis job (API.md: ``format=``), declared once for the
operation that checks a request and the task that writes the artifact."""

#: result format → (media type, file suffix) of the artifact
RESULT_FORMATS: dict[str, tuple[str, str]] = {
    "npz": ("application/x-npz", "npz"),
    "obj-exr-zip": ("application/zip", "zip"),
}
