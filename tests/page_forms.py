"""A page's form as a browser would post it: every field and hidden input the page drew (so the tokens and versions
the pages carry are posted back too)."""

from html.parser import HTMLParser


class PageForm(HTMLParser):
    """The fields of the first POST form whose action ends with ``action`` ("" for a form without one, which
    posts to its own page)."""

    def __init__(self, action):
        super().__init__()
        self.action, self.data, self.found, self._in = action, {}, False, False
        self._textarea = self._select = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "form" and not self.found and (a.get("method") or "").lower() == "post" \
                and (a.get("action") or "").endswith(self.action) and (self.action or not a.get("action")):
            self._in = self.found = True
        if not self._in:
            return
        if tag == "input" and a.get("name") and a.get("type") not in ("submit", "button"):
            if a.get("type") in ("checkbox", "radio") and "checked" not in a:
                return
            self.data[a["name"]] = a.get("value") or ""
        elif tag == "textarea":
            self._textarea = a["name"]
            self.data[self._textarea] = ""
        elif tag == "select":
            self._select = a["name"]
            self.data.setdefault(self._select, "")
        elif tag == "option" and self._select and "selected" in a:
            self.data[self._select] = a.get("value") or ""

    def handle_endtag(self, tag):
        if tag == "form":
            self._in = False
        elif tag == "textarea":
            self._textarea = None
        elif tag == "select":
            self._select = None

    def handle_data(self, data):
        if self._textarea:
            self.data[self._textarea] += data


def form_of(client, url, action="") -> dict:
    """The form's fields on the page at ``url`` (a GET with ``client``)."""
    r = client.get(url)
    assert r.status_code == 200, (url, r.status_code)
    return fields_of(r.content.decode(), action)


def fields_of(html: str, action="") -> dict:
    parser = PageForm(action)
    parser.feed(html)
    assert parser.found, f"no form posting to {action!r}"
    return parser.data
