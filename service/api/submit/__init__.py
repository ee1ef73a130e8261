"""HTTP side of a submission: request bodies read under one size policy (``forms``), the parts of a request
turned into the intake's typed inputs (``parts``), and the intake's answer as an HTTP response (``accept``).
The submission itself — storing, checking, validating, queueing — is :mod:`service.intake`."""
