"""The review page (``/ui/``): static HTML, CSS and JavaScript in ``static/``, no build step, nothing
fetched from outside the service; it talks to the JSON API with the API key the person enters."""
