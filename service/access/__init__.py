"""Who may use the service: API keys and roles (:mod:`~service.access.keys`), quotas per key
(:mod:`~service.access.quotas`) and signed webhooks (:mod:`~service.access.webhooks`).

Nothing here knows HTTP: the edge (:mod:`service.http.auth`) authenticates requests with a
:class:`~service.access.keys.KeyRing`, throttles them with a
:class:`~service.access.quotas.RateLimiter` and hands finished jobs to a
:class:`~service.access.webhooks.WebhookSender`. Keys are off by default (no
``FFS_API_KEYS`` nor ``FFS_API_KEYS_FILE``): everything is then open, as before.
"""
