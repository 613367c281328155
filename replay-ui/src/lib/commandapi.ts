/**
 * The command endpoints as the replay uses them: an operator's command (POST
 * /api/v1/commands) and the commands of a window with the robots' answers (GET). Every
 * refusal is an ApiError carrying the server's own message.
 */
import { send } from "./annotationapi";
import { getJson } from "./api";
import type { Command, CommandKind } from "./commands";

export class CommandApi {
  constructor(public base = "") {}

  async list(fromMs: number, toMs: number, robotId?: string): Promise<Command[]> {
    const robot = robotId ? `&robot=${encodeURIComponent(robotId)}` : "";
    const r = await getJson<{ commands: Command[] }>(
      `${this.base}/api/v1/commands?from=${Math.round(fromMs)}&to=${Math.round(toMs)}${robot}`, "the commands");
    return r.commands;
  }

  async send(robotId: string, kind: CommandKind, poiId?: string): Promise<Command> {
    const body = kind === "goto_poi" ? { robotId, kind, poiId } : { robotId, kind };
    return (await send<Command>("POST", `${this.base}/api/v1/commands`, body))!;
  }
}
