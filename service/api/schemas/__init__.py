"""What the API returns and documents: job status, summaries, links (``jobs``); the documented payloads
(geometry file, registration result, the multipart request body: ``payloads``)."""
