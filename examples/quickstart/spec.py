class USER:
    def __init__(self):
        self.verified = False
        self.asked_refund = False
    def VERIFY_IDENTITY(self): self.verified = True
    def ASK_REFUND(self): self.asked_refund = True

class AGENT:
    def __init__(self, user):
        self.user = user
    def GREET(self): pass
    def REQUEST_IDENTITY(self): pass
    def REFUND(self): pass
