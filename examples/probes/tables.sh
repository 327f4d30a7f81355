#!/bin/sh
# The report's tables alone, as one Markdown file: a script stage that is not Python. It reads
# the report it is given ($RLMFLOW_INPUT_REPORT) and writes into $RLMFLOW_OUTPUT only.
set -eu
report="$RLMFLOW_INPUT_REPORT/report.md"
grep -E '^(#|\|)' "$report" > "$RLMFLOW_OUTPUT/tables.md"
printf '@rlmflow {"summary": "%s table lines"}\n' "$(grep -c '^|' "$RLMFLOW_OUTPUT/tables.md")"
