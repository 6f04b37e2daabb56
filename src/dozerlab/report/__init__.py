"""The platform's HTML report (``results/report/index.html``).

Submodules: ``html`` (the shared building blocks: embedded images, tables with units, notes,
the page), ``sections`` (one module per section, each rendering its HTML from the results
directory), ``collect`` (per-point numbers and figures), ``build`` (composes the page), ``cli``
(``dozerlab report``). Kept import-light: the CLI imports this package to list its commands.
"""
