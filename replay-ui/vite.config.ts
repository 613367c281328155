import { resolve } from "node:path";
import { fileURLToPath } from "node:url";
import vue from "@vitejs/plugin-vue";
import { defineConfig } from "vitest/config";

// The API serves dist/ at "/" and "/controller"; `npm run dev` proxies the API instead.
const api = process.env.MAPSERVICE_API ?? "http://127.0.0.1:8080";

const root = fileURLToPath(new URL(".", import.meta.url));

export default defineConfig({
  plugins: [vue()],
  base: "/",
  build: {
    outDir: "dist",
    rollupOptions: {
      input: {
        main: resolve(root, "index.html"),
        controller: resolve(root, "controller.html"),
      },
    },
  },
  server: {
    proxy: {
      "/api": { target: api, ws: true },
    },
  },
  test: {
    include: ["tests/**/*.test.ts"],
    environment: "node",
  },
});
