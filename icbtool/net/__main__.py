"""``python -m icbtool.net docs/protocol.md``: rewrite the generated tables of the protocol
document from :data:`icbtool.net.protocol.KINDS`."""

import sys

from icbtool.net.protocol import update_doc

for doc in sys.argv[1:] or ["docs/protocol.md"]:
    print(f"{doc}: {'updated' if update_doc(doc) else 'up to date'}")
