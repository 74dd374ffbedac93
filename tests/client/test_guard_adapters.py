"""The adapters with the real frameworks, each driven by a scripted model against a stored set on a real stack,
judged in this process (`Guard`) and by the service (`ServiceGuard`): the model asks to cancel a reservation
before reading it (refused: the tool never runs, and the model's next input holds why), then reads it, then
cancels it (allowed: the tool runs).

OpenAI Agents SDK: its own `agents.testing.ScriptedModel`. LangGraph: a graph of a model node (LangChain's
`GenericFakeChatModel`, which answers a fixed list of messages) and the guarded `ToolNode`. LangChain's
`create_agent`: the same fake model (tools bound as given) with the guard as its middleware.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from precond.evaluation import tools
from precond.stack.keyed import KeyedStack
from precond_client import AsyncClient, Client, PreconditionSet
from precond_client.guard import Guard, Judge, ServiceGuard

if TYPE_CHECKING:
    from langchain_core.messages import BaseMessage
    from langgraph.graph import MessagesState

# Each test imports its framework itself: collecting this module (in every test process) stays cheap.

TAU = Path(__file__).resolve().parents[1] / "fixtures" / "tau_airline"
READ = "reservation_id in self.results['get_reservation_details']"
RESERVATION = {"reservation_id": "R1", "user_id": "u1", "cabin": "business", "insurance": "no"}


@pytest.fixture(scope="module")
def stored(keyed: KeyedStack) -> PreconditionSet:
    with Client(keyed.url, api_key=keyed.keys["guard"]) as client:
        return client.create_set({"spec": tools.load(TAU).spec,
                                  "preconditions": {"AGENT.cancel_reservation": [READ]}})


@pytest.fixture(params=["embedded", "service"])
def judge(request: pytest.FixtureRequest, stored: PreconditionSet, keyed: KeyedStack) -> Iterator[Judge]:
    if request.param == "embedded":
        with Client(keyed.url, api_key=keyed.keys["guard"]) as client:
            yield Guard.from_set(client.get_set(stored.reference))
    else:
        yield ServiceGuard(AsyncClient(keyed.url, api_key=keyed.keys["guard"]), stored.reference)


def scripted_calls() -> list[tuple[str, dict[str, str]]]:
    cancel = ("cancel_reservation", {"reservation_id": "R1"})
    return [cancel, ("get_reservation_details", {"reservation_id": "R1"}), cancel]


def airline_tools(decorator: Callable[[Callable[[str], str]], Any], ran: list[str]) -> tuple[Any, Any]:
    """The read and the cancellation as a framework's tools (`decorator`: its tool decorator), each noting in
    `ran` that it ran."""

    def get_reservation_details(reservation_id: str) -> str:
        """Read a reservation."""
        ran.append(f"get {reservation_id}")
        return json.dumps(RESERVATION)

    def cancel_reservation(reservation_id: str) -> str:
        """Cancel a reservation."""
        ran.append(f"cancel {reservation_id}")
        return json.dumps(RESERVATION | {"status": "cancelled"})

    return decorator(get_reservation_details), decorator(cancel_reservation)


def test_the_agents_sdk_guardrail_refuses_before_the_tool_runs_and_tells_the_model(judge: Judge) -> None:
    from agents import Agent, Runner, function_tool
    from agents.testing import ScriptedModel, assistant_message, function_call

    from precond_client.adapters.openai_agents import protect

    ran: list[str] = []
    get_reservation_details, cancel_reservation = airline_tools(function_tool, ran)

    steps = [[function_call(name, args, call_id=f"call-{n}")] for n, (name, args) in enumerate(scripted_calls())]
    model = ScriptedModel([*steps, [assistant_message("Cancelled.")]])
    agent = Agent(name="airline", model=model, tools=[get_reservation_details, cancel_reservation])
    result = asyncio.run(Runner.run(protect(agent, judge), "Please cancel R1."))
    assert result.final_output == "Cancelled."
    assert ran == ["get R1", "cancel R1"]  # the first cancellation never reached the tool
    refused = next(i for i in model.calls[1].input if i.get("type") == "function_call_output")
    assert refused["call_id"] == "call-0" and str(refused["output"]).startswith("Error: the precondition guard")
    assert f"`{READ}` does not hold" in str(refused["output"])
    outputs = [i for i in model.calls[3].input if i.get("type") == "function_call_output"]
    assert "cancelled" in str(outputs[-1]["output"])  # the allowed one ran and answered


def test_the_langgraph_tool_node_refuses_before_the_tool_runs_and_tells_the_model(judge: Judge) -> None:
    from langchain_core.language_models.fake_chat_models import GenericFakeChatModel
    from langchain_core.messages import AIMessage, HumanMessage, ToolMessage
    from langchain_core.tools import tool
    from langgraph.graph import START, MessagesState, StateGraph
    from langgraph.prebuilt import tools_condition

    from precond_client.adapters.langgraph import guarded_tool_node

    ran: list[str] = []
    get_reservation_details, cancel_reservation = airline_tools(tool, ran)

    answers = [AIMessage("", tool_calls=[{"name": name, "args": args, "id": f"call-{n}"}])
               for n, (name, args) in enumerate(scripted_calls())]
    model = GenericFakeChatModel(messages=iter([*answers, AIMessage("Cancelled.")]))
    seen: list[list[BaseMessage]] = []

    def call_model(state: MessagesState) -> dict[str, Any]:
        seen.append(list(state["messages"]))
        return {"messages": [model.invoke(state["messages"])]}

    graph = StateGraph(MessagesState)
    graph.add_node("model", call_model)
    graph.add_node("tools", guarded_tool_node([get_reservation_details, cancel_reservation], judge))
    graph.add_edge(START, "model")
    graph.add_conditional_edges("model", tools_condition)
    graph.add_edge("tools", "model")
    app = graph.compile()
    final = asyncio.run(app.ainvoke({"messages": [HumanMessage("Please cancel R1.")]},
                                    {"configurable": {"thread_id": "t1"}}))
    assert final["messages"][-1].content == "Cancelled."
    assert ran == ["get R1", "cancel R1"]
    refused = next(m for m in seen[1] if isinstance(m, ToolMessage))
    assert refused.status == "error" and refused.tool_call_id == "call-0"
    assert str(refused.content).startswith("Error: the precondition guard") and READ in str(refused.content)
    assert "cancelled" in str(seen[3][-1].content)


@pytest.mark.parametrize("run", ["invoke", "ainvoke"])
def test_the_create_agent_middleware_refuses_before_the_tool_runs_and_tells_the_model(
    judge: Judge, run: str, keyed: KeyedStack
) -> None:
    from langchain.agents import create_agent
    from langchain_core.language_models.fake_chat_models import GenericFakeChatModel
    from langchain_core.messages import AIMessage, HumanMessage, ToolMessage
    from langchain_core.tools import tool

    from precond_client.adapters.langchain_agents import GuardMiddleware

    class _ToolCallingFake(GenericFakeChatModel):
        """`create_agent` binds the tools to its model; the fake's answers already name them."""

        def bind_tools(self, tools: Any, **kwargs: Any) -> Any:
            return self

    ran: list[str] = []
    get_reservation_details, cancel_reservation = airline_tools(tool, ran)

    if run == "invoke" and isinstance(judge, ServiceGuard):  # a synchronous agent judges with a `Client`
        judge = ServiceGuard(Client(keyed.url, api_key=keyed.keys["guard"]), judge.reference)
    answers = [AIMessage("", tool_calls=[{"name": name, "args": args, "id": f"call-{n}"}])
               for n, (name, args) in enumerate(scripted_calls())]
    model = _ToolCallingFake(messages=iter([*answers, AIMessage("Cancelled.")]))
    agent = create_agent(model, tools=[get_reservation_details, cancel_reservation],
                         middleware=[GuardMiddleware(judge)])
    state = {"messages": [HumanMessage("Please cancel R1.")]}
    config: Any = {"configurable": {"thread_id": "t1"}}
    final = agent.invoke(state, config) if run == "invoke" else asyncio.run(agent.ainvoke(state, config))
    assert final["messages"][-1].content == "Cancelled."
    assert ran == ["get R1", "cancel R1"]  # the first cancellation never reached the tool
    results = [m for m in final["messages"] if isinstance(m, ToolMessage)]
    assert results[0].status == "error" and results[0].tool_call_id == "call-0"
    assert str(results[0].content).startswith("Error: the precondition guard") and READ in str(results[0].content)
    assert "cancelled" in str(results[-1].content)
