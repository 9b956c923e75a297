"""Headers every response of the clinic service carries.

The pages and the API show children's medical records, often on shared
workstations: nothing Django answers may be kept by a browser or a proxy
cache (static files are served before this middleware, by WhiteNoise, and stay
cacheable). The Content-Security-Policy allows only this site's own scripts,
styles and images (and data: images): the templates have no inline script or
style, and /api/docs runs django-ninja's bundled Swagger UI from static files.
"""

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
