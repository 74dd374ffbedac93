"""`precond mcp`: an MCP proxy in front of an agent's MCP servers that records every tool call as the OpenAI
messages `precond convert openai` reads, and judges each call with a precondition set first (docs/mcp.md).
Needs the official MCP SDK: `pip install "precond-client[mcp]"`."""
