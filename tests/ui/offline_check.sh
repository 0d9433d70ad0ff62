#!/usr/bin/env bash
# Issue 7 "offline": the built UI (ui/dist) asks nothing of the internet. Every absolute or
# protocol-relative URL in its HTML, JS and CSS must be an XML namespace (www.w3.org: names,
# never fetched), every CSS url()/@import must stay inside the bundle (relative or data:), and
# the page loads its script and style from relative paths. Prints each offending URL with its
# file; exit 1 if any, or when ui/dist is missing (the UI build failed).
# Usage: offline_check.sh UI_DIR
set -u
ui=${1:?usage: offline_check.sh UI_DIR}
dist=$ui/dist
[ -f "$dist/index.html" ] || { echo "FAIL: $dist/index.html is missing: the UI build (scripts/build.sh) failed or did not run"; exit 1; }
mapfile -t files < <(find "$dist" -type f \( -name '*.html' -o -name '*.js' -o -name '*.mjs' -o -name '*.css' \) | sort)
[ "${#files[@]}" -ge 2 ] || { echo "FAIL: expected the page and its assets in $dist, found ${#files[@]} file(s)"; exit 1; }
bad=0
for f in "${files[@]}"; do
  # Absolute (scheme://) and protocol-relative ("//host" in quotes or url()) references.
  while IFS= read -r u; do
    case "$u" in
      http://www.w3.org/*|https://www.w3.org/*) ;;  # namespaces (svg, xlink, xhtml)
      *) echo "FAIL: $(basename "$f") refers to $u"; bad=1 ;;
    esac
  done < <(grep -oE "[a-zA-Z][a-zA-Z0-9+.-]*://[^\"'\`) ]+|[\"'(]//[A-Za-z0-9-]+\.[A-Za-z0-9.-]+[^\"'\`) ]*" "$f" | grep -vE '^(ws|wss)://$' | sed -E "s/^[\"'(]//" | sort -u)
  if [[ $f == *.css ]]; then
    while IFS= read -r u; do
      case "$u" in
        data:*|./*|../*|/assets/*|assets/*|'') ;;
        *) echo "FAIL: $(basename "$f") loads $u from outside the bundle"; bad=1 ;;
      esac
    done < <(grep -oE "url\([^)]*\)|@import +[\"'][^\"']*[\"']" "$f" | sed -E "s/^url\(//; s/\)$//; s/^@import +//; s/[\"']//g" | sort -u)
  fi
done
while IFS= read -r ref; do
  case "$ref" in
    ./*|assets/*|/assets/*|'#'*|data:*) ;;
    *) echo "FAIL: index.html loads $ref (not a relative path in the bundle)"; bad=1 ;;
  esac
done < <(grep -oE "(src|href)=\"[^\"]*\"" "$dist/index.html" | sed -E 's/^(src|href)="//; s/"$//')
[ "$bad" = 0 ] && echo "ok: ${#files[@]} files in $dist, no outside URL (only XML namespaces)"
exit "$bad"
