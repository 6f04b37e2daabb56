"""The platform's HTML report (``results/report/index.html``) and the sweep's naming.

Submodules: ``points`` (sweep points and the workflow's result paths), ``html`` (a small
self-contained HTML page builder), ``collect`` (per-point figures and numbers from the
results), ``build`` (the report), ``cli`` (``dozerlab report``). Kept import-light: the CLI
imports this package to list its commands.
"""
