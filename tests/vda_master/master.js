// An independent VDA 5050 2.0 master (coatyio vda-5050-lib MasterController, inbound and outbound topic
// validation on) for tests/test_vda5050_master.py: it connects to the test's broker, assigns one order
// (drive, pick at the pallet node, drive, drop) to uagv/v2/palletpilot/<serial>, follows the AGV's state
// until the library reports the order processed, and prints one JSON summary line on stdout.
// Usage: node master.js PORT SERIAL ORDER_JSON_FILE TIMEOUT_S
"use strict";
const fs = require("fs");
const { MasterController, Topic } = require("vda-5050-lib");

const [port, serial, orderFile, timeoutS] = process.argv.slice(2);
const agvId = { manufacturer: "palletpilot", serialNumber: serial };
const order = JSON.parse(fs.readFileSync(orderFile, "utf8"));
const summary = {
  processed: false, error: null, byCancelation: null, actions: {}, loadsAfter: {}, errors: [],
  nodesTraversed: [], lastNodeId: null, states: 0,
};
let lastState = null;

const master = new MasterController(
  {
    interfaceName: "uagv",
    transport: { brokerUrl: `mqtt://127.0.0.1:${port}` },
    vdaVersion: "2.0.0",
    topicObjectValidation: { inbound: true, outbound: true },
  },
  { targetAgvs: agvId },
);

function finish(code) {
  if (lastState) {
    summary.lastNodeId = lastState.lastNodeId;
    summary.finalLoads = lastState.loads || [];
    summary.driving = lastState.driving;
  }
  process.stdout.write(JSON.stringify(summary) + "\n");
  master.stop().finally(() => process.exit(code));
}

setTimeout(() => { summary.error = `timeout after ${timeoutS} s`; finish(1); }, Number(timeoutS) * 1000);

(async () => {
  await master.start();
  await master.subscribe(Topic.State, agvId, (state) => {
    summary.states += 1;
    lastState = state;
    for (const e of state.errors || []) summary.errors.push(`${e.errorType}: ${e.errorDescription || ""}`);
  });
  await master.assignOrder(agvId, order, {
    onOrderProcessed(withError, byCancelation, active, context) {
      summary.processed = !withError && !active;
      summary.error = withError ? String(withError.message || withError) : null;
      summary.byCancelation = byCancelation;
      lastState = context.state;
      finish(withError ? 1 : 0);
    },
    onNodeTraversed(node) {
      summary.nodesTraversed.push(node.nodeId);
    },
    onActionStateChanged(actionState, withError, action, target, context) {
      const loads = (context.state.loads || []).map((l) => l.loadId || l.loadType || "");
      (summary.actions[action.actionId] = summary.actions[action.actionId] || []).push(actionState.actionStatus);
      if (actionState.actionStatus === "FINISHED") summary.loadsAfter[action.actionId] = loads;
      if (withError) summary.errors.push(`action ${action.actionId}: ${withError.message || withError}`);
    },
  });
})().catch((err) => { summary.error = String(err && err.stack ? err.stack : err); finish(1); });
