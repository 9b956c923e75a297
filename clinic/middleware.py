"""Headers every response of the clinic service carries.

The pages and the API show children's medical records, often on shared
workstations: nothing Django answers may be kept by a browser or a proxy
cache (static files are served before this middleware, by WhiteNoise, and stay
cacheable). The Content-Security-Policy allows only this site's own scripts,
styles and images (and data: images): the templates have no inline script or
style, and /api/docs runs django-ninja's bundled Swagger UI from static files.
"""

import time

from django.conf import settings
from django.utils.cache import add_never_cache_headers

CONTENT_SECURITY_POLICY = ("default-src 'self'; img-src 'self' data:; object-src 'none'; base-uri 'none'; "
                           "form-action 'self'; frame-ancestors 'none'")


class SecurityHeadersMiddleware:
    def __init__(self, get_response):
        self.get_response = get_response

    def __call__(self, request):
        response = self.get_response(request)
        response.setdefault("Content-Security-Policy", CONTENT_SECURITY_POLICY)
        # Cache-Control: no-store (with no-cache, must-revalidate, private, max-age=0) and an Expires in the past
        add_never_cache_headers(response)
        return response


class IdleSessionMiddleware:
    """A signed-in user's session ends ``SESSION_COOKIE_AGE`` after their last request (shared workstations).

    Instead of saving the session on every request (``SESSION_SAVE_EVERY_REQUEST``: a database write per page
    refresh and per status poll of a page), the session's expiry is pushed forward at most once every
    ``SESSION_REFRESH_SECONDS``; the idle timeout is then exact to within that interval. Runs inside Django's
    SessionMiddleware (listed after it), which saves a session marked modified.
    """

    KEY = "_refreshed"

    def __init__(self, get_response):
        self.get_response = get_response

    def __call__(self, request):
        response = self.get_response(request)
        session, user = getattr(request, "session", None), getattr(request, "user", None)
        if session is not None and user is not None and user.is_authenticated and not session.is_empty():
            now = int(time.time())
            if now - session.get(self.KEY, 0) >= settings.SESSION_REFRESH_SECONDS:
                session[self.KEY] = now  # modified: SessionMiddleware saves it, with a new expiry
        return response
