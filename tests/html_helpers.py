"""Reading an HTML page as a browser's parser sees it (tests of `hsicam report`)."""

from __future__ import annotations

from html.parser import HTMLParser


class PageParts(HTMLParser):
    """The image sources (``images``) and table cells (``cells``, their text) of a page."""

    def __init__(self, text: str):
        super().__init__()
        self.images: list[str] = []
        self.cells: list[str] = []
        self._in_cell = False
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs)["src"])
        elif tag == "td":
            self._in_cell = True
            self.cells.append("")

    def handle_endtag(self, tag):
        if tag == "td":
            self._in_cell = False

    def handle_data(self, data):
        if self._in_cell:
            self.cells[-1] += data
