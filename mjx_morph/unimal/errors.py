"""User-facing errors about robot files and robot values."""
from __future__ import annotations


class RobotError(ValueError):
    """A robot file or robot value outside the UNIMAL design space.

    The message always names the file (or robot), the element and what was expected, e.g.
    `robots/xml/a.xml: <geom name="limb/3">: type "box" is not allowed; expected "capsule"`.
    """

    def __init__(self, where: str, element: str, message: str):
        self.where = str(where)
        self.element = element
        self.message = message
        super().__init__(f"{self.where}: {element}: {message}" if element else f"{self.where}: {message}")
