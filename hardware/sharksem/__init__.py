"""TESCAN SEMs over SharkSEM, their remote-control protocol: the wire format
(:mod:`~hardware.sharksem.wire`), the link (:mod:`~hardware.sharksem.client`) and the SEM role
(:mod:`~hardware.sharksem.sem`)."""
