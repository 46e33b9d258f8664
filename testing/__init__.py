"""Test tools shipped with hapticproxy (not used by the server or the clients at run time).

- :mod:`.impair`: fault injection for datagram links (an impairing UDP relay, an impairing
  wrapper around any transport); :mod:`.impair_tcp`: an impairing TCP proxy for stream links.
- :mod:`.device_contract`: the contract suite every device driver passes (a lab runs it against
  its own driver, see that module).
- :mod:`.cleanup`: the body of a factory fixture that ends everything a test made.
"""
