#!/usr/bin/env bash
# The web page's end-to-end test drives Debian's chromium (never a browser download of its
# own). Part of the README's test command: installs chromium when it is missing and this is
# a Debian/Ubuntu machine where we are root; otherwise says why the browser test will skip.
set -u
if command -v chromium >/dev/null 2>&1 || [ -x /usr/bin/chromium ]; then
    exit 0
fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "tests: installing Debian's chromium for the web page test (apt-get) ..." >&2
    if (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium) \
        >/tmp/sarship-apt-chromium.log 2>&1; then
        echo "tests: chromium installed" >&2
    else
        echo "tests: could not install chromium (see /tmp/sarship-apt-chromium.log); the web page test will skip" >&2
    fi
else
    echo "tests: chromium is not installed (apt-get install chromium); the web page test will skip" >&2
fi
exit 0
