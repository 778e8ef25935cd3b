"""``ctgpp serve``: the playground in the browser (issue 19) — pick a scene, type a sentence, watch
the traffic.

- :mod:`~ctgpp.serve.scenes`: the scene sets the page may pick from, and a scene drawn as data.
- :mod:`~ctgpp.serve.schema`: what a browser may send (scene keys, sentences and numbers, bounded).
- :mod:`~ctgpp.serve.job_queue`: the queue of runs, one output folder each, cancellable, over worker
  processes; :mod:`~ctgpp.serve.job`: one run and what is known of it;
  :mod:`~ctgpp.serve.worker_handle`: the server's thread for each worker process;
  :mod:`~ctgpp.serve.worker`: what a worker process runs (:func:`ctgpp.simulate`);
  :mod:`~ctgpp.serve.models`: its models, loaded and warmed once when it starts.
- :mod:`~ctgpp.serve.frames`: the guided episode's frames as each re-plan finishes (streamed);
  :mod:`~ctgpp.serve.playback`: the finished rollout as the data the page animates.
- :mod:`~ctgpp.serve.app`: the HTTP routes (FastAPI) and the page (``static/``, plain HTML/JS/CSS).

The server process stays light and responsive: every simulation runs in a worker process.
"""
