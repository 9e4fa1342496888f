"""Family b: a second, independent sample actor generator (see :mod:`service.samples.family_b.actor`)."""
