"""The synthetic sample actor built on the ICT face rig (service/samples/data)."""
