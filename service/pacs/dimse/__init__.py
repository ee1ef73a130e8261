"""The DICOM (DIMSE) node: C-ECHO, C-STORE SCP, jobs from received studies, results by C-STORE.

* :mod:`.scp` — the acceptor (pynetdicom) and its association policy;
* :mod:`.inbox` — the durable index of received instances;
* :mod:`.grouping` — biplane pairs and the volume of one study;
* :mod:`.dispatcher` — stable studies → planned jobs, submitted by :mod:`.submit` through the intake
  (:mod:`service.intake`, as every submission; this package never imports the API);
* :mod:`.standalone` — ``dsareg dicom-listener``: the node and the intake in their own process;
* :mod:`.pull` — inputs by DIMSE reference (C-MOVE or C-GET);
* :mod:`.query` — C-FIND / C-MOVE SCU: the patient's latest volume, retrieval to our own AE;
* :mod:`.export` — the REG and overlays back to the peers by C-STORE (SCU);
* :mod:`.listener` — the node inside ``dsareg serve`` or alone (``dsareg dicom-listener``).

See ``docs/pacs/dimse.md`` and the conformance statement ``docs/pacs/conformance.md``.
"""
