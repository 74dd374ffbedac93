"""Agent frameworks' tool calls guarded by a precondition set: `openai_agents` (the OpenAI Agents SDK, extra
`precond-client[openai-agents]`) and `langgraph` (LangGraph's ToolNode, extra `precond-client[langgraph]`).
Each imports its framework; nothing here is imported by `precond_client` itself (docs/guard.md)."""
